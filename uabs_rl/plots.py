"""Figures: evaluated trajectories over the street map, P_g(N̂_s) curves, and the
style every report figure shares (sizes for a paper's columns, PNG and PDF)."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Circle  # noqa: E402

from uabs_rl.channel import beam_centres  # noqa: E402
from uabs_rl.config import AreaConfig, ScenarioConfig  # noqa: E402

COLORS = plt.rcParams["axes.prop_cycle"].by_key()["color"]
# a paper's single column and full text width (inches, IEEE two-column)
COLUMN_IN, TEXT_IN = 3.5, 7.16
# report figures: 8 pt text at print size, so they stay legible in a column
PAPER_RC = {"font.size": 8, "axes.titlesize": 8, "axes.labelsize": 8, "legend.fontsize": 7,
            "xtick.labelsize": 7, "ytick.labelsize": 7, "lines.linewidth": 1.2,
            "lines.markersize": 3.5, "axes.spines.top": False, "axes.spines.right": False,
            "pdf.fonttype": 42, "savefig.dpi": 300}
# learned policies in colour, one per masking mode; baselines in greys, one line style
# each, so the two never look alike
MODE_COLORS = {"penalty": "#d62728", "flat": "#1f77b4", "rank": "#2ca02c"}
BASELINE_STYLES = {"random": {"color": "0.6", "ls": ":", "marker": "v"},
                   "greedy": {"color": "0.35", "ls": "--", "marker": "s"},
                   "oracle": {"color": "0.0", "ls": "-.", "marker": "^"}}


def save_figure(fig, path: Path | str) -> list[Path]:
    """``path`` as PNG and PDF (vector, for a paper), cropped to the drawn content;
    returns the two files."""
    path = Path(path)
    outs = [path.with_suffix(".png"), path.with_suffix(".pdf")]
    for out in outs:
        fig.savefig(out, bbox_inches="tight")
    return outs


def save_paper_figure(draw, path: Path | str) -> list[Path]:
    """Draw (``draw()`` returns the figure) and save a report figure in the paper style
    (``PAPER_RC``: sizes, fonts, 300 dpi; ticks and text are laid out when saved, so
    both happen inside it), then close it; returns the PNG and PDF."""
    with plt.rc_context(PAPER_RC):
        fig = draw()
        files = save_figure(fig, path)
    plt.close(fig)
    return files


@lru_cache(maxsize=8)
def lane_segments(net_file: str, x0: float, y0: float) -> np.ndarray:
    """[K, 2, 2] line segments of every lane (internal ones included), area-relative."""
    from uabs_rl.traces import read_net

    net = read_net(net_file)
    segs = []
    for edge in net.getEdges(withInternal=True):
        for lane in edge.getLanes():
            shape = np.asarray(lane.getShape(), dtype=float) - (x0, y0)
            segs += [shape[i:i + 2] for i in range(len(shape) - 1)]
    return np.asarray(segs)


def scenario_lanes(scenario: ScenarioConfig) -> np.ndarray | None:
    """Lane segments of the scenario's network (None for a .sumocfg scenario)."""
    from uabs_rl.traces import scenario_inputs

    net = scenario_inputs(scenario)["net_file"]
    a = scenario.area
    return lane_segments(str(net), a.x_min, a.y_min) if net else None


def trajectory_figure(area: AreaConfig, uabs: torch.Tensor, vehicles: torch.Tensor,
                      present: torch.Tensor, r_b: float, n_beams: int,
                      lanes: np.ndarray | None = None, title: str = "",
                      instants: tuple[int, ...] | None = None):
    """One episode: ``uabs [T+1, M, 2]`` paths, ``vehicles [T+1, 2, V]`` (planar) with
    ``present [T+1, V]`` (drawn at the last instant, with their tracks faint), and beam
    footprints of every UABS at a few instants."""
    uabs, vehicles, present = uabs.cpu().numpy(), vehicles.cpu().numpy(), present.cpu().numpy()
    steps = uabs.shape[0]
    instants = instants or (0, steps // 2, steps - 1)
    fig, ax = plt.subplots(figsize=(8, 8 * area.height / area.width + 0.8), dpi=100)
    if lanes is not None and len(lanes):
        ax.add_collection(LineCollection(lanes, colors="0.8", linewidths=1.0, zorder=0))
    tracks = [vehicles[present[:, v], :, v] for v in range(vehicles.shape[2])]
    ax.add_collection(LineCollection([t for t in tracks if len(t)], colors="0.6",
                                     linewidths=0.4, zorder=1))  # one artist: fast to draw
    last = present[-1]
    ax.scatter(vehicles[-1, 0, last], vehicles[-1, 1, last], s=9, color="k", zorder=2,
               label="vehicles (last step)")
    centres = beam_centres(r_b, n_beams).numpy()
    for u in range(uabs.shape[1]):
        c = COLORS[u % len(COLORS)]
        ax.plot(uabs[:, u, 0], uabs[:, u, 1], color=c, lw=2, zorder=3, label=f"UABS {u}")
        ax.plot(*uabs[0, u], "o", color=c, ms=7, zorder=4)
        ax.plot(*uabs[-1, u], "*", color=c, ms=13, mec="k", zorder=4)
        for t in instants:
            for cx, cy in centres + uabs[t, u]:
                # add_artist, not add_patch: the limits are set below, and updating them
                # patch by patch took half of the picture's drawing time
                ax.add_artist(Circle((cx, cy), r_b, fill=False, ec=c, lw=0.7,
                                     alpha=0.3 + 0.7 * t / max(steps - 1, 1), zorder=2))
    ax.set_xlim(0, area.width)
    ax.set_ylim(0, area.height)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title or "UABS trajectories", fontsize=10)
    handles, _ = ax.get_legend_handles_labels()
    handles += [
        Line2D([], [], color="0.4", marker="o", ls="", ms=7, label="start (t = 0)"),
        Line2D([], [], color="0.4", marker="*", ls="", ms=12, mec="k",
               label=f"end (t = {steps - 1})"),
        Line2D([], [], color="0.4", marker="o", ls="", ms=9, mfc="none",
               label=f"beam footprints at t = {', '.join(map(str, instants))} "
                     f"(fainter = earlier)"),
        Line2D([], [], color="0.6", lw=0.6, label="vehicle tracks"),
    ] + ([Line2D([], [], color="0.8", lw=1.5, label="lanes")] if lanes is not None else [])
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8,
              frameon=False)
    fig.tight_layout()
    return fig


def pg_curve_figure(curves: dict[str, np.ndarray], title: str = "Satisfied users"):
    """P_g against N̂_s = 1..N, one line per label."""
    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    for i, (label, curve) in enumerate(curves.items()):
        x = np.arange(1, len(curve) + 1)
        c = COLORS[i % len(COLORS)]
        ax.plot(x, 100 * np.asarray(curve), marker="o", color=c, label=label)
    ax.set_xlabel(r"$\hat{N}_s$ (served steps required per window)")
    ax.set_ylabel(r"$P_g$ (% satisfied users)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    fig.tight_layout()
    return fig


BAND_LABEL = "shaded: 95 % bootstrap CI over seeds"


def _band_handle():
    from matplotlib.patches import Patch

    return Patch(facecolor="0.5", alpha=0.25, lw=0)


def return_curves_figure(curves: dict[str, tuple]):
    """Evaluation return against training episode: ``curves[label] = (mode, x, mean,
    lo, hi)``, one line with its band each, in the mode's colour. Penalty, whose
    collisions cost λ_c each, gets a panel (and scale) of its own so it does not
    flatten the masking modes into one line. Drawn for :func:`save_paper_figure`."""
    from matplotlib.ticker import MaxNLocator

    groups = [[k for k, c in curves.items() if c[0] != "penalty"],
              [k for k, c in curves.items() if c[0] == "penalty"]]
    groups = [g for g in groups if g]
    fig, axes = plt.subplots(1, len(groups), squeeze=False,
                             figsize=(TEXT_IN if len(groups) > 1 else COLUMN_IN, 2.4))
    for ax, labels in zip(axes[0], groups, strict=True):
        modes = [curves[k][0] for k in labels]
        for label in labels:
            mode, x, mean, lo, hi = curves[label]
            c = MODE_COLORS.get(mode, "0.3")
            ax.plot(x, mean, color=c, label=label)
            ax.fill_between(x, lo, hi, color=c, alpha=0.2, lw=0)
        ax.set_xlabel("training episode")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_title(" and ".join(modes) + (" masking" if modes != ["penalty"] else
                                             " (reward penalties)"))
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("validation return R")
    handles = [h for ax in axes[0] for h in ax.get_legend_handles_labels()[0]]
    labels = [lab for ax in axes[0] for lab in ax.get_legend_handles_labels()[1]]
    fig.legend([*handles, _band_handle()], [*labels, BAND_LABEL], loc="upper center",
               bbox_to_anchor=(0.5, 0.0), ncol=len(labels) + 1 if len(groups) > 1 else 2,
               frameon=False)
    fig.tight_layout()
    return fig


def pg_panels_figure(panels: dict[str, tuple], baselines: dict[str, dict[str, np.ndarray]]):
    """P_g(N̂_s) in %, one panel per masking mode: ``panels[mode] = (seeds text, mean,
    lo, hi)`` for the learned policy, ``baselines[mode][name]`` the baselines' curves
    under the same masks, in greys with their own line styles. Drawn for
    :func:`save_paper_figure`."""
    modes = list(panels)
    fig, axes = plt.subplots(1, len(modes), squeeze=False, sharey=True,
                             figsize=(TEXT_IN if len(modes) > 1 else COLUMN_IN, 2.4))
    for ax, mode in zip(axes[0], modes, strict=True):
        seeds, mean, lo, hi = panels[mode]
        x = np.arange(1, len(mean) + 1)
        c = MODE_COLORS.get(mode, "0.3")
        ax.plot(x, mean, color=c, marker="o",
                label=f"learned, {mode}" + (" masks" if mode != "penalty" else ""))
        ax.fill_between(x, lo, hi, color=c, alpha=0.2, lw=0)
        for name, curve in baselines.get(mode, {}).items():
            ax.plot(x, curve, lw=1, label=f"{name} baseline", **BASELINE_STYLES[name])
        ax.set_title(f"{mode} masks ({seeds})" if mode != "penalty"
                     else f"penalty ({seeds})")
        ax.set_xlabel(r"$\hat{N}_s$ (served steps per window)")
        ax.set_xticks(x[::max(1, len(x) // 5)])
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel(r"$P_g$ (% satisfied users)")
    seen: dict[str, object] = {}
    for ax in axes[0]:
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            seen.setdefault(lab, h)
    order = sorted(seen, key=lambda lab: not lab.startswith("learned"))  # learned first
    handles = [seen[lab] for lab in order] + [_band_handle()]
    fig.legend(handles, [*order, BAND_LABEL], loc="upper center", bbox_to_anchor=(0.5, 0.0),
               ncol=min(len(handles), 4 if len(modes) > 1 else 2), frameon=False)
    fig.tight_layout()
    return fig


def animate_episode(area: AreaConfig, uabs: torch.Tensor, vehicles: torch.Tensor,
                    present: torch.Tensor, r_b: float, n_beams: int,
                    lanes: np.ndarray | None, path, fps: int = 8,
                    returns: torch.Tensor | None = None, title: str = "") -> None:
    """A GIF of one episode: vehicles, UABS with their beam footprints, paths so far, a
    legend, and with ``returns`` (``[T+1]``, the return after each step) a running
    return counter."""
    from matplotlib.animation import FuncAnimation, PillowWriter

    uabs, vehicles, present = uabs.cpu().numpy(), vehicles.cpu().numpy(), present.cpu().numpy()
    ret = None if returns is None else returns.cpu().numpy()
    centres = beam_centres(r_b, n_beams).numpy()
    fig, ax = plt.subplots(figsize=(8.5, 7 * area.height / area.width + 0.6), dpi=80)
    handles = [Line2D([], [], color=COLORS[u % len(COLORS)], lw=1.5, marker="*", ms=10,
                      mec="k", label=f"UABS {u} (path so far)") for u in range(uabs.shape[1])]
    handles += [Line2D([], [], color="0.4", marker="o", ls="", ms=9, mfc="none",
                       label="beam footprints"),
                Line2D([], [], color="k", marker=".", ls="", label="vehicles")]

    def draw(t: int):
        ax.clear()
        if lanes is not None and len(lanes):
            ax.add_collection(LineCollection(lanes, colors="0.8", linewidths=1.0))
        on = present[t]
        ax.scatter(vehicles[t, 0, on], vehicles[t, 1, on], s=8, color="k")
        for u in range(uabs.shape[1]):
            c = COLORS[u % len(COLORS)]
            ax.plot(uabs[: t + 1, u, 0], uabs[: t + 1, u, 1], color=c, lw=1.5)
            ax.plot(*uabs[t, u], "*", color=c, ms=12, mec="k")
            for cx, cy in centres + uabs[t, u]:
                ax.add_patch(Circle((cx, cy), r_b, fill=False, ec=c, lw=0.8))
        ax.set_xlim(0, area.width)
        ax.set_ylim(0, area.height)
        ax.set_aspect("equal")
        counter = f"t = {t} / {uabs.shape[0] - 1}"
        if ret is not None:
            counter += f"    return so far R = {ret[t]:.0f}"
        ax.set_title(f"{title}\n{counter}" if title else counter, fontsize=10)
        ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0),
                  fontsize=8, frameon=False)

    anim = FuncAnimation(fig, draw, frames=uabs.shape[0])
    fig.subplots_adjust(left=0.06, right=0.72)
    anim.save(str(path), writer=PillowWriter(fps=fps))
    plt.close(fig)
