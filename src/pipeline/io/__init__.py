"""Input and output: raw frames, the dataset layout, its validation, and the artefact files."""
