"""Statistics shared by the stages and the diagnostics: least squares, streaming moments, bootstraps, match-ups."""
