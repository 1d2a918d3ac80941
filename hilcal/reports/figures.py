"""What the report's plots share: margins fixed in inches, plain-number log axes and PNG as base64.

Every run writes its report's plots, so their cost is paid at every run's end. Margins are set from the known sizes
of the labels instead of measured by a layout engine (tight_layout or constrained layout draws every text once more),
and a log axis labels its ticks as plain numbers (0.001) instead of typeset powers of ten (mathtext parsing).
matplotlib is imported when the first figure is made, not with the report modules: a run imports them at its start,
and one stopped before its report (a refusal, a killed process) would pay 0.8 CPU s for nothing.
"""

from __future__ import annotations

import base64
import io
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure


def new_figure(width_in: float, height_in: float) -> Figure:
    """A matplotlib Figure without pyplot (no global state, no GUI backend)."""
    from matplotlib.figure import Figure

    return Figure(figsize=(width_in, height_in))


def fixed_margins(fig: Figure, *, left_in: float, right_in: float, bottom_in: float, top_in: float,
                  wspace_in: float = 0.0, hspace_in: float = 0.0) -> None:
    """Place the subplot grid with margins and gaps in inches (gaps between the axes of a grid)."""
    width, height = fig.get_size_inches()
    grid = fig.axes[0].get_subplotspec().get_gridspec() if fig.axes else None
    nrows, ncols = grid.get_geometry() if grid is not None else (1, 1)
    axes_w = (width - left_in - right_in - wspace_in * (ncols - 1)) / ncols
    axes_h = (height - bottom_in - top_in - hspace_in * (nrows - 1)) / nrows
    fig.subplots_adjust(left=left_in / width, right=1.0 - right_in / width, bottom=bottom_in / height,
                        top=1.0 - top_in / height, wspace=wspace_in / axes_w, hspace=hspace_in / axes_h)


def plain_log_scale(ax: Axes) -> None:
    """A log y axis whose decades read 0.001, 0.01, ... (no typeset 10^-3, no minor labels)."""
    from matplotlib.ticker import FuncFormatter, NullFormatter

    ax.set_yscale("log")
    ax.yaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
    ax.yaxis.set_minor_formatter(NullFormatter())


def png_base64(fig: Figure, dpi: int = 100) -> str:
    """The figure as a PNG, base64 (for a data URI: the page opens offline)."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi)
    return base64.b64encode(buffer.getvalue()).decode("ascii")
