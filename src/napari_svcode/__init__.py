"""napari-svcode: the napari plugin. Thin: it calls :mod:`svcode_core` and adds layers."""

__version__ = "0.1.0"
