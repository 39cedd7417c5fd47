"""Exports of a model to the formats other tools read (nerfstudio, COLMAP, PLY/3DGS, OpenCV).

See :mod:`opacityhull.export.formats`; the CLI is ``opacityhull export``.
"""
