"""Phase-measuring deflectometry: the §1.10 setup with a display of sinusoidal fringes in place of the markers.

* :mod:`scopetwin.recon.fringes.phase` — N-step phase retrieval, phase noise, temporal multi-frequency unwrapping
  -> the display point (u, v) of every pixel with its uncertainty and validity (:func:`decode_display`);
* :mod:`scopetwin.recon.fringes.slopes` — dense slopes through the project's ray model (§1.6, §1.7);
* :mod:`scopetwin.recon.fringes.integration` — sparse B-spline integration of the slopes with a curvature prior and
  posterior samples;
* :mod:`scopetwin.recon.fringes.two_positions` — the absolute height per pixel from two display positions (§1.3);
* :mod:`scopetwin.recon.fringes.reconstruct` — the nested start-height iteration (§1.4) and
  :func:`reconstruct_fringes`.

Input is plain arrays (the frames, or decoded display coordinates) and a setup, as on a real rig; nothing here
imports Mitsuba or sim.
"""
