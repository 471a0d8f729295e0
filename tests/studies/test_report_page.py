"""The shared report page (opnav.studies.report_page) and plot helpers (opnav.studies.report_plots)."""

from __future__ import annotations

import base64
import hashlib
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest

from opnav.epochs import parse_epoch, to_time
from opnav.studies.report_page import Figure, Table, provenance, write_page
from opnav.studies.report_plots import envelope_indices, figure_png, new_figure, utc_axis, utc_dates

REPO = Path(__file__).resolve().parents[2]


def _png() -> bytes:
    fig, axes = new_figure(width_in=3, height_in=2)
    axes[0, 0].plot([0, 1], [0, 1])
    return figure_png(fig)


def test_page_has_figures_tables_and_provenance(tmp_path):
    png = _png()
    run_file = tmp_path / "run.toml"
    run_file.write_text("[scenario]\nstudy = 's1'\n")
    prov = provenance(["opnav", "run", str(run_file), "--out", "x y"], run_file)
    blocks = ["## Errors", "Text with `code` and a | pipe.", Figure("ekf_rtn", "Errors in RTN.", png),
              Table("Paper", ("quantity", "paper", "opnav"), (("RMS (km)", "1.0", "1.1"),), note="Ref. [1]")]
    write_page(tmp_path, "Run x", blocks, prov)
    page = (tmp_path / "report.html").read_text()
    md = (tmp_path / "report.md").read_text()
    assert (tmp_path / "figures" / "ekf_rtn.png").read_bytes() == png
    # the HTML carries the PNG itself, inside the figure element of its id
    figure = re.search(r"<figure id='fig-ekf_rtn'><img [^>]*src='data:image/png;base64,([^']+)'", page)
    assert figure is not None and base64.b64decode(figure.group(1)) == png
    assert "<section id='provenance'>" in page and "## Provenance" in md
    assert hashlib.sha256(run_file.read_bytes()).hexdigest() in page
    assert "'x y'" in page  # the command line shell-quoted
    assert "<code>code</code>" in page and "<td>RMS (km)</td>" in page and "Ref. [1]" in page
    assert "| RMS (km) | 1.0 | 1.1 |" in md and "![ekf_rtn](figures/ekf_rtn.png)" in md


def test_figure_ids_are_checked(tmp_path):
    with pytest.raises(ValueError, match="figure id"):
        Figure("EKF errors", "x", b"")
    prov = provenance(None, None)
    with pytest.raises(ValueError, match="repeat"):
        write_page(tmp_path, "t", [Figure("a", "x", b"1"), Figure("a", "y", b"2")], prov)
    with pytest.raises(ValueError, match="cells"):
        Table("t", ("a", "b"), (("1",),))


def test_provenance_names_the_checkout_revision():
    prov = provenance(None, None)
    head = subprocess.run(["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True, text=True)
    if head.returncode != 0:
        assert prov.git_revision is None
    else:
        assert prov.git_revision == head.stdout.strip()
    assert prov.command is None and prov.run_file_sha256 is None
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", prov.date_utc)


def test_utc_dates_match_astropy_per_epoch():
    # 40 days across the leap second of 2016-12-31: the interpolated dates agree with astropy's own to 1 s
    start = parse_epoch("2016-12-10T00:00:00", "utc")
    t = start + np.sort(np.random.default_rng(1).uniform(0.0, 40 * 86_400.0, 500))
    exact = to_time(t).utc.plot_date
    assert np.max(np.abs(utc_dates(t) - exact)) * 86_400.0 < 1.0
    fig, axes = new_figure()
    x = utc_axis(axes[0, 0], t)
    assert np.array_equal(x, utc_dates(t)) and axes[0, 0].get_xlabel() == "UTC"


def test_envelope_keeps_the_extremes():
    values = np.random.default_rng(2).normal(size=100_000)
    keep = envelope_indices(values, 400)
    assert keep.size <= 402 and np.all(np.diff(keep) > 0)
    assert values[keep].max() == values.max() and values[keep].min() == values.min()


def test_calendar_axes_find_ticks_for_any_span_without_a_warning():
    """Arcs from a minute to two years on panels a third of a page wide: matplotlib's own tick steps left
    gaps (a 2.4-hour window warned 'unable to pick an appropriate interval'); none may warn. Each figure's
    three panels (their own x axes) carry three neighbouring spans of the 42, so 14 figures are drawn
    rather than one per span."""
    import warnings

    import numpy as np

    from opnav.studies.report_plots import figure_png, new_figure, utc_axis

    spans = np.geomspace(60.0, 730 * 86400.0, 42).reshape(14, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for row in spans:
            fig, axes = new_figure(1, 3)
            for ax, span in zip(axes[0], row):
                ax.plot(utc_axis(ax, 4.5e8 + np.linspace(0.0, span, 50)), np.sin(np.arange(50)))
            figure_png(fig)
