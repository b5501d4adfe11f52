"""One-shot calibration on exact synthetic marker positions (thesis §2.8.1, §2.8.2, §2.8.5) and its speed.

Prints our deviations beside the thesis's Tables 2.2, 2.3, 2.4 and 2.8, OpenCV's solvePnP (ITERATIVE, SQPNP
with the true intrinsics) as the peer, and the time of one calibration (linear + non-linear) for 24-1000
markers. Run: ``PYTHONPATH=. python benchmarks/calibration_oneshot.py``.
"""

from __future__ import annotations

import sys
import time
import warnings
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from calibration_common import fmt, frame_dev, pose_error, solvepnp  # noqa: E402

from scopetwin.calib.oneshot import CalibrationWarning, Prior, calibrate  # noqa: E402
from scopetwin.scenes.setup import load_setup  # noqa: E402

warnings.simplefilter("ignore", CalibrationWarning)

SEED_22 = {"linear": {"r": "(1.432e-07, 5.017e-06, -2.842e-14)"}, "non-linear": {"r": "(1.79e-13, -6.787e-14, 0)"}}
SEED_23 = {
    "linear": {"r": "(-1.557e-15, 4.366e-01, -1.485e-02)", "b": "2.6e-03"},
    "non-linear": {"r": "(6.071e-15, 3.126e-13, 3.979e-13)", "b": "0"},
}


def case(name: str):
    s = load_setup(name)
    pat = s.marker_pattern
    prior = Prior.from_camera(s.camera_model, s.camera.focal_length, r_cs=(0.0, 0.0), c0=1.0, c2=0.0)
    return s, pat.centers_local(), s.camera_model.project(pat.centers()), prior


def table(title: str, name: str, lens: str, seed: dict) -> None:
    s, xy, px, prior = case(name)
    cal = calibrate(xy, px, prior, lens=lens)
    truth = s.camera_model
    print(f"\n== {title} ({name}, lens={cal.lens}, {len(xy)} markers)")
    for label, cam in (("linear", cal.linear.camera), ("non-linear", cal.camera)):
        d = frame_dev(cam.frame, truth.frame)
        print(f"  {label:10s} Δr_c = {fmt(d['r'])} mm   seed: {seed[label]['r']} mm")
        print(f"  {'':10s} ΔT_x = {fmt(d['T_x'])}  ΔT_y = {fmt(d['T_y'])}  ΔN_z = {fmt(d['N_z'])}")
        print(
            f"  {'':10s} Δb = {cam.b - truth.b:.3e} mm"
            + (f"   seed: {seed[label]['b']} mm" if "b" in seed[label] else "")
        )
    res = cal.camera.project(np.column_stack([xy, np.zeros(len(xy))])) - px
    rr = np.linalg.norm(res, axis=1) * prior.pitch
    lres = cal.linear.camera.project(np.column_stack([xy, np.zeros(len(xy))])) - px
    lr = np.linalg.norm(lres, axis=1) * prior.pitch
    print(
        f"  marker centres: linear rms {np.sqrt(np.mean(lr**2)):.3e} mm, pv {np.ptp(lr):.3e} mm; non-linear rms "
        f"{np.sqrt(np.mean(rr**2)):.3e} mm, pv {np.ptp(rr):.3e} mm"
    )
    print(
        f"  linear magnification: m_x = {cal.linear.m_x:.8f}, m_y = {cal.linear.m_y:.8f} "
        f"(disagreement {cal.linear.m_disagreement:.2e})"
    )
    for flag, fname in ((cv2.SOLVEPNP_ITERATIVE, "ITERATIVE"), (cv2.SOLVEPNP_SQPNP, "SQPNP+LM")):
        e, a = pose_error(solvepnp(xy, px, truth, flag), truth.frame)
        print(f"  OpenCV solvePnP {fname:9s}: |Δr_c| = {e:.3e} mm, rotation {a:.3e} rad (true intrinsics)")
    e, a = pose_error(cal.camera.frame, truth.frame)
    print(f"  ours                      : |Δr_c| = {e:.3e} mm, rotation {a:.3e} rad")


def noise_experiment(draws: int = 500) -> None:
    s, xy, px, prior = case("thesis-2.8.1-angular")
    truth = s.camera_model
    sigma = 0.233e-3 / prior.pitch
    rng = np.random.default_rng(24)
    print(f"\n== §2.8.2 noise: sigma 0.233 µm on the marker images, {draws} draws, 30° view (Table 2.4: one draw)")
    print("   seed (with distortion): Δr_c = (1.09e-3, 5.72e-3, 6.91e-3) mm, ΔT_y = (7.31e-6, 1.03e-5, 6.21e-6)")
    for lens in ("fixed", "thin-lens", "free", "auto"):
        d, dt, dn, sig, used = [], [], [], [], []
        for _ in range(draws):
            cal = calibrate(xy, px + rng.normal(0.0, sigma, px.shape), prior, lens=lens)
            d.append(cal.camera.center - truth.center)
            dt.append(cal.camera.frame.ty - truth.frame.ty)
            dn.append(cal.camera.frame.nz - truth.frame.nz)
            sig.append(cal.sigma["r_c"])
            used.append(cal.lens)
        rms = lambda a: np.sqrt(np.mean(np.square(a), axis=0))  # noqa: E731
        print(
            f"  {lens:9s}: rms Δr_c = {fmt(rms(d))} mm (mean {fmt(np.mean(d, axis=0))}), mean reported "
            f"σ(r_c) = {fmt(np.mean(sig, axis=0))} mm"
        )
        print(
            f"  {'':9s}  rms ΔT_y = {fmt(rms(dt))}, rms ΔN_z = {fmt(rms(dn))}"
            + (f"; auto chose free in {used.count('free')}/{draws}" if lens == "auto" else "")
        )


def distortion_case() -> None:
    s, xy, px, prior = case("thesis-2.8.5-distortion")
    truth = s.camera_model
    print("\n== §2.8.5 distortion and offset (Table 2.8)")
    print("   seed: Δr_c = (2.62e-6, 34.0, 20.4) µm, Δr_cs = (0.02, 7.94) µm, Δc0 = 2.47e-4, Δc2 = 9.11e-7")
    for lens in ("thin-lens", "free"):
        cal = calibrate(xy, px, prior, lens=lens, distortion=True)
        c = cal.camera
        print(
            f"  {lens:9s}: Δr_c = {fmt(c.center - truth.center, 1e3)} µm, Δr_cs = "
            f"{fmt(np.subtract(c.r_cs, truth.r_cs), 1e3)} µm, Δc0 = {c.c0 - truth.c0:.3e}, "
            f"Δc2 = {c.c2 - truth.c2:.3e}"
            f", c0*b - b_true = {c.c0 * c.b - truth.b:.2e} mm, rms {cal.residual_rms_px * prior.pitch:.2e} mm"
        )
    cal = calibrate(xy, px, prior, lens="thin-lens", distortion=False)
    print(
        f"  without offset/distortion: rms {cal.residual_rms_px * prior.pitch:.3e} mm, pv "
        f"{cal.residual_pv_px * prior.pitch:.3e} mm (the thesis: 8.553e-4 / 1.542e-3 mm)"
    )


def speed() -> None:
    s = load_setup("thesis-2.8.1-angular")
    cam = s.camera_model
    print("\n== speed: one calibration (linear + non-linear), angular view, exact positions + 0.01 px noise")
    rng = np.random.default_rng(5)
    for nx, ny, pitch in ((6, 4, 8.0), (11, 9, 4.0), (20, 15, 2.4), (40, 25, 1.2)):
        i, j = np.meshgrid(np.arange(nx), np.arange(ny))
        xy = np.column_stack([(i.ravel() - (nx - 1) / 2) * pitch, (j.ravel() - (ny - 1) / 2) * pitch])
        px = cam.project(np.column_stack([xy, np.zeros(len(xy))]))
        assert cam.in_image(px).all()
        px = px + rng.normal(0, 0.01, px.shape)
        prior = Prior.from_camera(cam, 25.0)
        for lens in ("thin-lens", "auto", "free"):
            calibrate(xy, px, prior, lens=lens)  # warm
            n = 20
            t0 = time.perf_counter()
            for _ in range(n):
                cal = calibrate(xy, px, prior, lens=lens)
            ms = (time.perf_counter() - t0) / n * 1e3
            print(
                f"  {len(xy):5d} markers, lens={lens:9s}: {ms:6.2f} ms per calibration "
                f"(nfev {cal.nfev}, used {cal.lens}; target <= 50 ms)"
            )


def main() -> None:
    table("§2.8.1 perpendicular view, Table 2.2", "thesis-2.8.1-perpendicular", "fixed", SEED_22)
    table(
        "§2.8.1 perpendicular view, the thesis's thin-lens b",
        "thesis-2.8.1-perpendicular",
        "thin-lens",
        SEED_22,
    )
    table("§2.8.1 angular view, Table 2.3", "thesis-2.8.1-angular", "auto", SEED_23)
    table("§2.8.1 angular view, the thesis's thin-lens b", "thesis-2.8.1-angular", "thin-lens", SEED_23)
    noise_experiment()
    distortion_case()
    speed()


if __name__ == "__main__":
    main()
