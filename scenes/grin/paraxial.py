"""Analytic paraxial (ABCD) optics of GRIN rods and the layered objective (thesis §7.5, §8.3).

Ray vectors are (y, n·u): height and reduced angle, so flat interfaces are the identity and
every matrix has determinant 1. A rod with paraxial profile n ≈ n0 (1 - g² r² / 2) and length L:

    [[cos gL,            sin gL / (n0 g)],
     [-n0 g sin gL,      cos gL         ]]

A homogeneous slab of thickness t and index n: [[1, t/n], [0, 1]].

For a single rod in air: pitch P = 2π/g, effective focal length f = 1 / (n0 g sin gL),
back focal (working) distance s = cot(gL) / (n0 g) = f cos gL.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from scopetwin.scenes.grin.profiles import RadialProfile
from scopetwin.scenes.grin.setup import Stack

Matrix = NDArray[np.float64]


def slab(thickness: float, index: float) -> Matrix:
    """Transfer through a homogeneous slab (reduced-angle form)."""
    return np.array([[1.0, thickness / index], [0.0, 1.0]])


def grin_rod(profile: RadialProfile, length: float) -> Matrix:
    """Paraxial matrix of a radial GRIN rod of ``length`` (flat faces included)."""
    g, n0 = profile.g, profile.n0
    c, s = np.cos(g * length), np.sin(g * length)
    return np.array([[c, s / (n0 * g)], [-n0 * g * s, c]])


@dataclass(frozen=True)
class RodParaxial:
    """Paraxial data of a single rod in air (mm)."""

    pitch: float
    efl: float
    bfl: float
    g: float
    n0: float


def rod_paraxial(profile: RadialProfile, length: float) -> RodParaxial:
    """Pitch 2π/g, EFL 1/(n0 g sin gL) and working distance cot(gL)/(n0 g) of one rod."""
    g, n0 = profile.g, profile.n0
    return RodParaxial(2 * np.pi / g, 1.0 / (n0 * g * np.sin(g * length)), 1.0 / (n0 * g * np.tan(g * length)), g, n0)


def stack_matrix(stack: Stack, start: int = 0, stop: int | None = None) -> Matrix:
    """Product of the layer matrices ``start`` .. ``stop`` - 1 (default: all but the image gap)."""
    stop = len(stack.layers) - 1 if stop is None else stop
    m = np.eye(2)
    for layer in stack.layers[start:stop]:
        mat = (
            grin_rod(layer.profile, layer.thickness)
            if layer.profile is not None
            else slab(layer.thickness, layer.index)
        )
        m = mat @ m
    return m


@dataclass(frozen=True)
class SystemParaxial:
    """Paraxial data of the objective: object plane -> last surface -> paraxial image."""

    efl: float
    image_distance: float
    magnification: float
    matrix: Matrix


def system_paraxial(stack: Stack) -> SystemParaxial:
    """EFL = -1/C, image distance d = -B/D (air), magnification 1/D of the object-to-last-surface matrix."""
    m = stack_matrix(stack)
    a, b, c, d = m.ravel()
    n_img = stack.layers[-1].index
    image_distance = -b / d * n_img
    return SystemParaxial(-n_img / c, image_distance, 1.0 / d, m)


def magnification_at(stack: Stack, image_distance: float) -> float:
    """Paraxial chief-ray-free magnification y'/y at an image plane ``image_distance`` past the last surface.

    At a defocused plane the image of a point is a blur; this is the height of the ray that leaves
    the object point parallel to nothing in particular -- the A element of the full matrix, i.e.
    the magnification of the ray through the centre of a pupil at infinity. Used only to compare
    readings at a fixed image plane.
    """
    m = slab(image_distance, stack.layers[-1].index) @ stack_matrix(stack)
    return float(m[0, 0])
