"""Data files of pregrasp: the hand URDF and its meshes, and the demo objects.

This folder is installed as the package ``pregrasp_assets`` so that a plain ``pip install``
finds the files; use :mod:`pregrasp_core.paths` to locate them.
"""
