"""Step-response figure of `evorobotics.analysis`: wheel commands after each single contact.

Matplotlib Agg only, drawn from an `Analysis` (no simulation here); like `plots.py`, PNGs carry
no version metadata, so the same analysis gives the same bytes.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np

from evorobotics.analysis import Analysis
from evorobotics.plots import PNG_METADATA

WHEELS = (("left", "tab:blue"), ("right", "tab:red"))


def responses_plot(analysis: Analysis, path: Path) -> None:
    """One panel per input: left/right commands against step for a one-step contact at 0.

    Solid lines are the response, dashed the zero-input reference; the grey band is the contact
    step, the dotted vertical line where the response settled (title: steps, or "no").
    """
    singles = [c for c in analysis.contacts if c.duration == 1 and len(c.inputs) == 1]
    if not singles:
        raise ValueError("analysis has no single-input contact to plot")
    reference = np.asarray(analysis.reference)
    ends = [c.settle_steps if c.settle_steps is not None else c.new_steady_steps for c in singles]
    last = len(singles[0].motors) - 1 + analysis.trace_start
    # zoom on the transient unless some panel never settles
    xmax = last if None in ends else min(last, max(10, *[e or 0 for e in ends]) + 5)
    fig, axes = plt.subplots(
        1, len(singles), figsize=(2.6 * len(singles) + 0.6, 3.4), sharey=True, squeeze=False
    )
    for ax, contact in zip(axes[0], singles, strict=True):
        motors = np.asarray(contact.motors)
        steps = np.arange(motors.shape[0]) + analysis.trace_start
        ax.axvspan(-0.5, 0.5, color="lightgrey", alpha=0.6, linewidth=0)
        for k, (name, colour) in enumerate(WHEELS[: motors.shape[1]]):
            ax.plot(steps, reference[: motors.shape[0], k], "--", color=colour, linewidth=0.8)
            ax.plot(steps, motors[:, k], ".-", color=colour, markersize=3, label=name)
        if contact.settle_steps is not None:
            ax.axvline(contact.settle_steps, color="black", linestyle=":", linewidth=0.8)
            verdict = f"settles in {contact.settle_steps}"
        elif contact.new_steady_steps is not None:
            verdict = f"new steady state in {contact.new_steady_steps}"
        else:
            verdict = "does not settle"
        ax.set_title(f"{contact.label}: {verdict}", fontsize=9)
        ax.set_xlabel("step after contact")
        ax.set_ylim(-1.05, 1.05)
        ax.set_xlim(analysis.trace_start - 0.5, xmax + 0.5)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("wheel command")
    axes[0][0].legend(loc="lower right", fontsize=8)
    fig.suptitle(
        f"controller {analysis.sha256[:12]}: response to a one-step contact "
        f"(baseline {analysis.baseline.kind}, tol {analysis.settle_tol:g})",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110, metadata=PNG_METADATA)
    plt.close(fig)
