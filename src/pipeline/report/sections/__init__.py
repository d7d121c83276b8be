"""One module per report section; each registers its builder with :func:`pipeline.report.registry.section`."""
