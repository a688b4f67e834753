"""Racetracks: the built-in library, track files (TOML, or CSV of gate poses), the informed and
uniform generators (SPEC §7), the held-out validation and test sets, and the closed smoothing
spline the informed generator fits.

A track argument anywhere in dronerace is a `Track`, a library track's name ("Figure8") or the
path of a track file or of a directory of them.
"""

from dronerace._core import Track
from dronerace._core import fit as fit
from dronerace._core import generate as generate
from dronerace._core import library as library
from dronerace._core import library_names as library_names
from dronerace._core import load as load
from dronerace._core import parse as parse
from dronerace._core import test_set as test_set
from dronerace._core import validation_set as validation_set

testset = test_set

__all__ = ["Track", "fit", "generate", "library", "library_names", "load", "parse", "test_set", "testset", "validation_set"]
