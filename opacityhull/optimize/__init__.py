"""Fitting the surfels to the photographs by differentiable EWA splatting (issue 29):
``raster`` is the differentiable CPU rasterizer, ``raster_reference`` its NumPy twin;
``fit`` the fitting (:func:`~opacityhull.optimize.fit.fit_model`), the other modules
its parts (SH appearance, SSIM, Adam, densification, data, the splat PLY)."""
