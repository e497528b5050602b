"""bimfactor: coarse-to-fine robot localization against a building's BIM model (IFC)."""

__version__ = "0.1.0"
