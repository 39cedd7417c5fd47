"""Browser viewer: a static WebGL2 bundle (ULR blending in the shader, EWA-style splats).

See :mod:`opacityhull.view.bundle` and ``docs/viewer-format.md``; the CLI is ``opacityhull view``.
"""
