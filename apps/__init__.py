"""Programs people run: ``python -m apps.<name>``."""
