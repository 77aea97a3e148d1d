"""Figures: evaluated trajectories over the street map, P_g(N̂_s) curves, and the
style every report figure shares (sizes for a paper's columns, PNG and PDF)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Circle  # noqa: E402

from uabs_rl.config import AreaConfig, ScenarioConfig  # noqa: E402
from uabs_rl.env.channel import beam_centres  # noqa: E402
from uabs_rl.safety.rules import masks_collisions  # noqa: E402

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
                   "oracle": {"color": "0.0", "ls": "-.", "marker": "^"},
                   # uabs-report --planner: the upper reference
                   "planner": {"color": "0.0", "ls": "-", "marker": "*"}}


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
    from uabs_rl.traces.inputs import read_net

    net = read_net(net_file)
    segs = []
    for edge in net.getEdges(withInternal=True):
        for lane in edge.getLanes():
            shape = np.asarray(lane.getShape(), dtype=float) - (x0, y0)
            segs += [shape[i:i + 2] for i in range(len(shape) - 1)]
    return np.asarray(segs)


def scenario_lanes(scenario: ScenarioConfig) -> np.ndarray | None:
    """Lane segments of the scenario's network (None for a .sumocfg scenario)."""
    from uabs_rl.traces.inputs import scenario_inputs

    net = scenario_inputs(scenario)["net_file"]
    a = scenario.area
    return lane_segments(str(net), a.x_min, a.y_min) if net else None


def _agg_figure(size: tuple[float, float], dpi: int = 100) -> Figure:
    """A figure drawn by Agg, outside pyplot's list of open figures: a run keeps its
    evaluation pictures open (a population two per member; pyplot warns past 20)."""
    fig = Figure(figsize=size, dpi=dpi)
    FigureCanvasAgg(fig)
    return fig


def _map_axes(area: AreaConfig, legend_in: float = 2.5, map_in: float = 6.0):
    """A figure whose axes hold exactly the area at equal scale (``map_in`` inches along
    its longer side), with a column for the legend at the right: no empty band above or
    below the map, whether the figure is saved cropped or rendered as it is."""
    aspect = area.height / area.width
    ax_w, ax_h = (map_in, map_in * aspect) if aspect <= 1 else (map_in / aspect, map_in)
    left, bottom, top, gap = 0.75, 0.5, 0.35, 0.15
    fig_w = left + ax_w + gap + legend_in
    fig_h = max(bottom + ax_h + top, 2.8)  # the legend's height, for a very flat area
    fig = _agg_figure((fig_w, fig_h))
    ax = fig.add_axes((left / fig_w, (fig_h - top - ax_h) / fig_h, ax_w / fig_w, ax_h / fig_h))
    ax.set_xlim(0, area.width)
    ax.set_ylim(0, area.height)
    ax.set_aspect("equal")
    return fig, ax


class LivePicture:
    """A figure drawn in full once; afterwards only its ``changing`` artists are drawn
    again, over a copy of the rest (matplotlib's blitting). A run's evaluation pictures
    change in their paths, curves and titles only: redrawn so, they take a few
    milliseconds instead of a full build and draw (~0.3 s each evaluation)."""

    def __init__(self, fig, changing):
        self.fig, self.changing = fig, list(changing)
        self._background = None
        for artist in self.changing:
            artist.set_animated(True)  # left out of the full draw: the background

    def render(self) -> np.ndarray:
        """The picture, ``[H, W, 4]`` uint8 (a view of the canvas, valid until the next
        render)."""
        canvas = self.fig.canvas
        if self._background is None:
            canvas.draw()
            self._background = canvas.copy_from_bbox(self.fig.bbox)
        else:
            canvas.restore_region(self._background)
        for artist in self.changing:
            self.fig.draw_artist(artist)
        return np.asarray(canvas.buffer_rgba())


class TrajectoryPicture:
    """One episode over the street map, cropped to the area: the UABS paths (a circle at
    the start, a star at the end) with the beam footprints of every UABS at a few
    instants, over ``vehicles [T+1, 2, V]`` with ``present [T+1, V]``: the position of
    every vehicle at every step as a small grey dot (dotted tracks, never lines, so they
    do not read as lanes) and at the last step as a black dot; lanes as thin light-grey
    lines. The map is drawn once; :meth:`update` places the ``n_uabs`` paths of an
    episode over the same vehicles (a run's evaluation window), and with ``live``
    ``self.live.render()`` redraws only them (:class:`LivePicture`; ``self.live`` is
    None otherwise)."""

    def __init__(self, area: AreaConfig, vehicles: torch.Tensor, present: torch.Tensor,
                 r_b: float, n_beams: int, n_uabs: int, lanes: np.ndarray | None = None,
                 instants: tuple[int, ...] | None = None, live: bool = False):
        self.vehicles, self.present = vehicles, present
        vehicles, present = vehicles.cpu().numpy(), present.cpu().numpy()
        steps = vehicles.shape[0]
        self.instants = instants or (0, steps // 2, steps - 1)
        fig, ax = _map_axes(area)
        self.fig, self.ax = fig, ax
        if lanes is not None and len(lanes):
            ax.add_collection(LineCollection(lanes, colors="0.82", linewidths=0.6, zorder=0),
                              autolim=False)
        t_on, v_on = np.nonzero(present)
        ax.scatter(vehicles[t_on, 0, v_on], vehicles[t_on, 1, v_on], s=2.5, color="0.3",
                   alpha=0.6, lw=0, zorder=1,
                   rasterized=True)  # one artist, an image in the PDF: a district's 50 000
        # points would be 50 000 vector markers (slow to write, slow to open)
        last = present[-1]
        ax.scatter(vehicles[-1, 0, last], vehicles[-1, 1, last], s=9, color="k", zorder=2)
        self.centres = beam_centres(r_b, n_beams).numpy()
        self.footprints: list[tuple[int, int, int, Circle]] = []  # (UABS, step, beam, circle)
        self.paths, self.marks = [], []  # marks: start and end of each UABS, in turn
        for u in range(n_uabs):
            c = COLORS[u % len(COLORS)]
            for t in self.instants:
                for k in range(len(self.centres)):
                    # add_artist, not add_patch: the limits are fixed, and updating them
                    # patch by patch took half of the picture's drawing time
                    circle = Circle((0.0, 0.0), r_b, fill=False, ec=c, lw=0.7,
                                    alpha=0.3 + 0.7 * t / max(steps - 1, 1), zorder=2)
                    self.footprints.append((u, t, k, ax.add_artist(circle)))
            self.paths.append(ax.plot([], [], color=c, lw=2, zorder=3, label=f"UABS {u}")[0])
            self.marks += [ax.plot([], [], "o", color=c, ms=7, zorder=4)[0],
                           ax.plot([], [], "*", color=c, ms=13, mec="k", zorder=4)[0]]
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_title("UABS trajectories", fontsize=10)
        handles, _ = ax.get_legend_handles_labels()
        handles += [
            Line2D([], [], color="0.4", marker="o", ls="", ms=7, label="start (t = 0)"),
            Line2D([], [], color="0.4", marker="*", ls="", ms=12, mec="k",
                   label=f"end (t = {steps - 1})"),
            Line2D([], [], color="0.4", marker="o", ls="", ms=9, mfc="none",
                   label=f"beam footprints at t = {', '.join(map(str, self.instants))}\n"
                         f"(fainter = earlier)"),
            Line2D([], [], color="k", marker="o", ls="", ms=3,
                   label=f"vehicles at t = {steps - 1}"),
            Line2D([], [], color="0.3", marker="o", ls="", ms=2,
                   label="vehicle positions, every step"),
        ] + ([Line2D([], [], color="0.82", lw=1.0, label="lanes")] if lanes is not None else [])
        ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8,
                  frameon=False, borderaxespad=0)
        # drawn in z-order over the background, which holds the axes' frame: footprints
        # cross the frame where a full draw puts them under it (a few pixels)
        self.live = LivePicture(self.fig, [*(f[-1] for f in self.footprints), *self.paths,
                                           *self.marks, ax.title]) if live else None

    def shows(self, vehicles: torch.Tensor, present: torch.Tensor) -> bool:
        """Whether the map holds these vehicles (else a new picture is needed)."""
        return torch.equal(vehicles, self.vehicles) and torch.equal(present, self.present)

    def update(self, uabs: torch.Tensor, title: str = "") -> None:
        """Place the paths ``uabs [T+1, M, 2]`` and the title."""
        uabs = uabs.cpu().numpy()
        for u, path in enumerate(self.paths):
            path.set_data(uabs[:, u, 0], uabs[:, u, 1])
            self.marks[2 * u].set_data(uabs[:1, u, 0], uabs[:1, u, 1])
            self.marks[2 * u + 1].set_data(uabs[-1:, u, 0], uabs[-1:, u, 1])
        for u, t, k, circle in self.footprints:
            circle.set_center(self.centres[k] + uabs[t, u])
        self.ax.title.set_text(title or "UABS trajectories")


def trajectory_figure(area: AreaConfig, uabs: torch.Tensor, vehicles: torch.Tensor,
                      present: torch.Tensor, r_b: float, n_beams: int,
                      lanes: np.ndarray | None = None, title: str = "",
                      instants: tuple[int, ...] | None = None):
    """The figure of :class:`TrajectoryPicture` for the paths ``uabs [T+1, M, 2]``."""
    pic = TrajectoryPicture(area, vehicles, present, r_b, n_beams, uabs.shape[1], lanes,
                            instants)
    pic.update(uabs, title)
    return pic.fig


class PgCurvePicture:
    """P_g (%) against N̂_s = 1..``n``, one line per label, on fixed axes (0 to 100 %):
    a run's evaluations compare at a glance, and with ``live`` ``self.live.render()``
    redraws only the lines and the title (:class:`LivePicture`)."""

    def __init__(self, labels: list[str], n: int, live: bool = False):
        fig = _agg_figure((6, 4))
        ax = fig.subplots()
        self.fig, self.ax = fig, ax
        self.lines = [ax.plot([], [], marker="o", color=COLORS[i % len(COLORS)],
                              label=label)[0] for i, label in enumerate(labels)]
        ax.set_xlim(1 - 0.05 * max(n - 1, 1), n + 0.05 * max(n - 1, 1))
        ax.set_ylim(-5, 105)
        ax.set_xlabel(r"$\hat{N}_s$ (served steps required per window)")
        ax.set_ylabel(r"$P_g$ (% satisfied users)")
        ax.set_title("Satisfied users")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
        self.fig.tight_layout()
        self.live = LivePicture(self.fig, [*self.lines, ax.title]) if live else None

    def update(self, curves: list[np.ndarray], title: str = "Satisfied users") -> None:
        for line, curve in zip(self.lines, curves, strict=True):
            line.set_data(np.arange(1, len(curve) + 1), 100 * np.asarray(curve))
        self.ax.title.set_text(title)


def pg_curve_figure(curves: dict[str, np.ndarray], title: str = "Satisfied users"):
    """The figure of :class:`PgCurvePicture` for these curves."""
    n = max(len(c) for c in curves.values())
    pic = PgCurvePicture(list(curves), n)
    pic.update(list(curves.values()), title)
    return pic.fig


BAND_ALPHA = 0.2
# below this many points per line, each point gets a marker (two evaluations drawn as a
# bare straight line read as a measured trend)
FEW_POINTS = 15


@dataclass
class SeedCurve:
    """One line of a report figure: the mean over ``seeds`` seeds at ``x`` and its spread
    (``lo``/``hi``: a 95 % CI, the min-max range with 2 seeds, nothing with 1; see
    :func:`uabs_rl.evaluation.stats.spread_over_seeds`)."""

    label: str
    x: np.ndarray
    mean: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    seeds: int
    color: str
    mode: str = ""


def _draw_curve(ax, c: SeedCurve, **kw) -> None:
    """The mean with markers where there are few points, and its band where there is one
    (more than one seed)."""
    few = len(c.x) < FEW_POINTS
    ax.plot(c.x, c.mean, color=c.color, label=c.label,
            **{"marker": "o" if few else None, **kw})
    if c.seeds > 1:
        ax.fill_between(c.x, c.lo, c.hi, color=c.color, alpha=BAND_ALPHA, lw=0)


def band_label(curves: list[SeedCurve]) -> str | None:
    """The legend's words for the shaded bands of ``curves``; None where none is drawn."""
    seeds = {c.seeds for c in curves if c.seeds > 1}
    if not seeds:
        return None
    if seeds == {2}:
        return "shaded: min-max range of the 2 seeds"
    return "shaded: 95 % CI, Student-t over seeds" + (
        " (min-max range where 2 seeds)" if 2 in seeds else "")


def _band_handle():
    from matplotlib.patches import Patch

    return Patch(facecolor="0.5", alpha=0.25, lw=0)


def _figure_legend(fig, axes, curves: list[SeedCurve], ncol: int, first: str = "") -> None:
    """One legend below the panels: each label once (those starting with ``first``
    first), then the band's meaning where a band is drawn."""
    seen: dict[str, object] = {}
    for ax in axes:
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            seen.setdefault(lab, h)
    order = sorted(seen, key=lambda lab: not lab.startswith(first)) if first else list(seen)
    handles, labels = [seen[lab] for lab in order], order
    band = band_label(curves)
    if band:
        handles, labels = [*handles, _band_handle()], [*labels, band]
    fig.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, 0.0),
               ncol=max(1, min(len(labels), ncol)), frameon=False)


def return_curves_figure(curves: list[SeedCurve]):
    """Evaluation return against training episode, one line (with its band) per curve.
    Penalty (``mode``), whose collisions cost λ_c each, gets a panel (and scale) of its
    own so it does not flatten the masking modes into one line. Drawn for
    :func:`save_paper_figure`."""
    from matplotlib.ticker import MaxNLocator

    groups = [[c for c in curves if masks_collisions(c.mode)],
              [c for c in curves if not masks_collisions(c.mode)]]
    groups = [g for g in groups if g]
    fig, axes = plt.subplots(1, len(groups), squeeze=False,
                             figsize=(TEXT_IN if len(groups) > 1 else COLUMN_IN, 2.4))
    for ax, group in zip(axes[0], groups, strict=True):
        modes = list(dict.fromkeys(c.mode for c in group))
        for c in group:
            _draw_curve(ax, c)
        ax.set_xlabel("training episode")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        masked = any(masks_collisions(m) for m in modes)
        ax.set_title(" and ".join(modes) + (" masking" if masked else " (reward penalties)"))
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("validation return R")
    few = len(curves) <= 3 and all(len(c.label) < 30 for c in curves)
    _figure_legend(fig, axes[0], curves, ncol=len(curves) + 1 if few else 2)
    fig.tight_layout()
    return fig


def pg_panels_figure(panels: dict[str, list[SeedCurve]],
                     baselines: dict[str, dict[str, np.ndarray]],
                     titles: dict[str, str] | None = None):
    """P_g(N̂_s) in %, one panel per key of ``panels`` (a masking mode, or a mode with the
    scenario settings its baselines were run under): the learned curves of that panel,
    and ``baselines[key][name]``, the baselines' curves under the same masks, in greys
    with their own line styles. ``titles[key]`` heads each panel (default: the key).
    Drawn for :func:`save_paper_figure`."""
    keys = list(panels)
    fig, axes = plt.subplots(1, len(keys), squeeze=False, sharey=True,
                             figsize=(TEXT_IN if len(keys) > 1 else COLUMN_IN, 2.4))
    for ax, key in zip(axes[0], keys, strict=True):
        x = np.arange(1, len(panels[key][0].mean) + 1)
        for c in panels[key]:
            _draw_curve(ax, c, marker="o")
        for name, curve in baselines.get(key, {}).items():
            label = "planner (knows the future)" if name == "planner" else f"{name} baseline"
            ax.plot(x, curve, lw=1, label=label, **BASELINE_STYLES[name])
        ax.set_title((titles or {}).get(key, key))
        ax.set_xlabel(r"$\hat{N}_s$ (served steps per window)")
        ax.set_xticks(x[::max(1, len(x) // 5)])
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel(r"$P_g$ (% satisfied users)")
    curves = [c for cs in panels.values() for c in cs]
    long = any(len(c.label) > 30 for c in curves)
    _figure_legend(fig, axes[0], curves, ncol=4 if len(keys) > 1 and not long else 2,
                   first="learned")
    fig.tight_layout()
    return fig


def run_curves_figure(runs: list[tuple[str, str, np.ndarray, np.ndarray, np.ndarray,
                                       np.ndarray]]):
    """Training and validation return of several runs overlaid, one line per run:
    ``runs[i] = (label, colour, training episodes, training returns, evaluation
    episodes, validation returns)``. Training returns are a moving mean over a 50th of
    the episodes (raw when fewer than 100), so curves of 1000 episodes stay readable.
    Drawn for :func:`save_paper_figure`."""
    from matplotlib.ticker import MaxNLocator

    styles = ["-", "--", ":", "-."]
    fig, (tr, ev) = plt.subplots(1, 2, figsize=(TEXT_IN, 2.6))
    seen: dict[str, int] = {}
    for label, color, ep, ret, eval_ep, eval_ret in runs:
        ls = styles[seen.setdefault(color, 0) % len(styles)]  # seeds of a group: styles
        seen[color] += 1
        w = max(1, len(ep) // 50)
        smooth = np.convolve(ret, np.ones(w) / w, mode="valid") if len(ret) >= w else ret
        tr.plot(np.asarray(ep)[w - 1:][:len(smooth)], smooth, color=color, ls=ls, lw=1,
                marker="o" if len(smooth) < FEW_POINTS else None, label=label)
        ev.plot(eval_ep, eval_ret, color=color, ls=ls,
                marker="o" if len(eval_ep) < FEW_POINTS else None, label=label)
    longest = max((len(r[2]) for r in runs), default=0)
    window = max(1, longest // 50)
    tr.set_title("training return" + (f" (moving mean over {window} episodes)"
                                      if window > 1 else ""))
    ev.set_title("validation return")
    for ax in (tr, ev):
        ax.set_xlabel("training episode")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.grid(alpha=0.3)
    tr.set_ylabel("return R")
    handles, labels = ev.get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, 0.0),
               ncol=2 if len(runs) > 3 or any(len(lab) > 30 for lab in labels) else 3,
               frameon=False)
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
