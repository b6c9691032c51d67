"""The package's version (here, at the floor, so every layer can record it)."""

__version__ = "0.1.0"
