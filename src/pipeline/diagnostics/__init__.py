"""Closure and missing-effect diagnostics: residual tests, closures across experiments, plausibility, findings."""
