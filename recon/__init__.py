"""recon: from camera images to surfaces — markers, gradients, heights, focus maps (no Mitsuba).

Modules by the thesis's sections:

* :mod:`scopetwin.recon.markers` — marker identification (§1.5, §2.6): ``centroid_search`` (§1.5.1), ``filtering``
  (§1.5.2),
  ``grid_identification`` (§1.5.3, §2.6.1), ``indexing`` (§1.5.4, :func:`scopetwin.recon.markers.index_grid`),
  ``identification`` (all four, from a setup);
* :mod:`scopetwin.recon.bias` — the centroid-bias model (§1.5.1 centroids of markers imaged through §1.6 / §2.8.2
  optics);
* :mod:`scopetwin.recon.gradients` — normals and gradients from camera and pattern rays (§1.7);
* :mod:`scopetwin.recon.shifted_basis` — height reconstruction with shifted basis functions (§1.8);
* :mod:`scopetwin.recon.frame_criterion` — the frame criterion of the outer loop (§1.4, eqs. 1.3-1.4);
* :mod:`scopetwin.recon.reconstruct` — the nested start-height iteration (§1.4); rays meet the surface by
  :func:`scopetwin.scenes.secant.secant_intersection` (§1.6.4);
* :mod:`scopetwin.recon.focusmap` — focus maps from the reconstructed surface (§1.1: removing the focus search).
"""

if __name__ == "recon":  # the bare folder, from the checkout's root: a second copy of scopetwin.recon
    raise ImportError(
        "recon is part of scopetwin: import scopetwin.recon (install with `make setup` or `pip install -e .`)"
    )
