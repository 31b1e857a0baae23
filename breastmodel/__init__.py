"""Subject-specific breast biomechanics: the application layer (pipeline, phantoms, CLI)."""

__version__ = "0.1.0"
