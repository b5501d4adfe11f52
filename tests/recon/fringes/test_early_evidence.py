"""The fringe frame loop's early evidence search: started once, near the criterion's root, on the same slopes whether
it runs in a second thread or at once; a failed search reaches the caller."""

from __future__ import annotations

import pytest

from scopetwin.recon import parallel
from scopetwin.recon.fringes import reconstruct as fr
from scopetwin.recon.posterior import PosteriorError


@pytest.mark.parametrize("cpus", [1, 2])
def test_the_search_starts_once_near_the_root_on_one_cpu_or_two(monkeypatch, cpus: int) -> None:
    monkeypatch.setattr(parallel, "available_cpus", lambda: cpus)
    seen: list[str] = []

    def fit(obs):
        seen.append(obs)
        return f"prior of {obs}"

    early = fr._EarlyEvidence(fit, wanted=True)
    try:
        near = fr.EVIDENCE_EARLY_UM * 1e-3  # mm
        early.offer(2.0 * near, "slopes twice EVIDENCE_EARLY_UM from the root")  # not yet
        assert early.result() is None
        early.offer(-0.4 * near, "slopes near the root")
        early.offer(1e-6, "slopes at the root")  # one search only
        assert early.result() == "prior of slopes near the root"
    finally:
        early.close()
    assert seen == ["slopes near the root"]


@pytest.mark.parametrize("cpus", [1, 2])
def test_a_failed_search_reaches_the_caller_and_an_unwanted_one_never_runs(monkeypatch, cpus: int) -> None:
    monkeypatch.setattr(parallel, "available_cpus", lambda: cpus)

    def too_few(obs):
        raise PosteriorError("5 gradient observations are too few for the evidence")

    early = fr._EarlyEvidence(too_few, wanted=True)
    try:
        early.offer(0.0, "slopes")
        with pytest.raises(PosteriorError, match="too few"):
            early.result()
    finally:
        early.close()
    off = fr._EarlyEvidence(too_few, wanted=False)
    off.offer(0.0, "slopes")
    assert off.result() is None
    off.close()
