"""Fitting the surfels to the photographs by differentiable EWA splatting (issue 29):
``raster`` is the differentiable CPU rasterizer, ``raster_reference`` its NumPy twin."""
