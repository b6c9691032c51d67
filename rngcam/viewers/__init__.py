"""Readers that put rngcam files into other programs' viewers (napari: `napari_reader`)."""
