"""Gaussian splatting: projection, tile binning and compositing, spherical harmonics, pictures."""
