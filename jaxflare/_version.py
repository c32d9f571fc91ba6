"""The package version, in one place (the stages import it from here, not from the package)."""

__version__ = "0.1.0"
