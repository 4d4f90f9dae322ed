"""Rasterisation: tile binning, A-buffer surface reconstruction, compositing (Section 6.4)."""
