"""Optimized opacity hull: the hull's surfels fitted to the photographs by
differentiable EWA splatting (issue 29). ``raster`` is the differentiable rasterizer;
``fit`` the fitting (:func:`~opacityhull.optimize.fit.fit_model`); the other modules
are its parts (SH appearance, SSIM, Adam, densification, data, the splat PLY)."""
