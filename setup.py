"""Package discovery for setuptools (everything else is in pyproject.toml).

Every package under ``archive/`` is found (``find_namespace_packages``: data folders such as the
viewer's ``static/`` too), plus the two top-level folders that ship as ``archive.shaders`` and
``archive.catalogs`` (``package-dir`` in pyproject.toml). pyproject.toml's ``packages.find`` cannot
express the second part, and a hand-written list left ``archive.outputs`` out of the wheel.
"""

from setuptools import find_namespace_packages, setup

setup(packages=sorted({*find_namespace_packages(include=["archive", "archive.*"], exclude=["*.__pycache__"]),
                       "archive.shaders", "archive.catalogs"}))
