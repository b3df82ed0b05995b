"""Frequency-sweep identification of the rate-loop plant: :func:`bode_plot`, a PNG of data, fit and coherence,
headed by the fitted figures (:func:`~hil.analysis.fit_caption`).

Docs: docs/ident.md.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hil.analysis._frf import Frf
from hil.analysis._plant import PlantFit, fit_caption


def bode_plot(
    frf: Frf, fit: PlantFit | None, path: str | Path, *, title: str | None = None, coherence_min: float = 0.8
) -> Path:
    """Magnitude (dB) and phase (deg) against log frequency: data (grey below ``coherence_min``), fit (the fitted
    band shaded), coherence; ``fit`` may be None. ``title`` (e.g. the session's name, default "plant
    identification") heads the plot, the fitted figures (:func:`fit_caption`) under it; the page grows to hold the
    whole heading (constrained layout, tight bounding box), and the PNG's Title and Description hold the same two
    texts. Returns the PNG's path (parent directories are created)."""
    from matplotlib.figure import Figure as MplFigure  # noqa: PLC0415  (heavy: loaded only when a figure is drawn)

    out = Path(path)
    f = frf.freq_hz
    head = title or "plant identification"
    caption = fit_caption(fit) if fit is not None else "no fit"
    fig = MplFigure(figsize=(8.0, 6.5), layout="constrained")
    ax_m, ax_p = fig.subplots(2, 1, sharex=True)
    mag, ph = frf.magnitude_db(), frf.phase_deg()
    model = None
    if fit is not None:  # data phase shown around the model's: no unwrapping through incoherent bins
        model = fit.response(f)
        ph_m = np.degrees(np.unwrap(np.angle(model)))
        ph = ph_m + np.degrees(np.angle(frf.response / model))
    ax_c = ax_m.twinx()
    ax_c.fill_between(f, 0.0, frf.coherence, color="tab:green", alpha=0.12, step="mid", label="coherence")
    ax_c.set_ylim(0.0, 1.05)
    ax_c.set_ylabel("coherence", color="tab:green")
    good = frf.coherence >= coherence_min
    for ax, v in ((ax_m, mag), (ax_p, ph)):
        ax.semilogx(f[good], v[good], ".", ms=2.5, color="tab:blue", label=f"data ({frf.method})")
        ax.semilogx(f[~good], v[~good], ".", ms=2.0, color="0.7", label=f"coherence < {coherence_min:g}")
    if fit is not None and model is not None:
        ax_m.semilogx(f, 20.0 * np.log10(np.abs(model)), "-", color="tab:red", label="fit")
        ax_p.semilogx(f, ph_m, "-", color="tab:red", label="fit")
        lo, hi = fit.f_range_hz
        for ax in (ax_m, ax_p):
            ax.axvspan(lo, hi, color="0.5", alpha=0.06, lw=0)
    ax_m.set_ylabel("|y/u| (dB re 1 deg/s per count)")
    ax_p.set_ylabel("phase (deg)")
    ax_p.set_xlabel("frequency (Hz)")
    for ax in (ax_m, ax_p):
        ax.grid(True, which="both", alpha=0.3)
        ax.patch.set_visible(False)
    ax_m.set_zorder(ax_c.get_zorder() + 1)  # data and legend over the coherence shading
    ax_m.legend(loc="lower left", fontsize=8)
    fig.suptitle(head, fontsize=11, fontweight="bold")
    ax_m.set_title(caption, fontsize=9)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110, format="png", bbox_inches="tight", pad_inches=0.1,
                metadata={"Title": head, "Description": caption})
    return out
