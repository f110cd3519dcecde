"""The calibration report: one self-contained ``report.html`` per run directory (issue 17, item 4).

What a customer keeps of a calibration: which robot or machine was measured
with which instrument, what the data checks said, the accuracy before and after
(identification and held-out sets), the plots, the identified parameters, the
compensation check and the exact versions and config. It is written from the
run directory's files alone (:mod:`torchcal.report.rundata`), opens offline
(inline CSS, images as ``data:`` URIs, no script, no external URL) and prints
to PDF cleanly (``@media print`` rules). Any kind of run gives a report: a
file the run lacks turns its section into "not available", never an error.

    >>> from torchcal.report import write_report
    >>> write_report("data/fanuc/runs")                       # doctest: +SKIP
    PosixPath('data/fanuc/runs/report.html')
"""

from __future__ import annotations

from pathlib import Path

from .rundata import Missing, ReportError, RunFiles, get, read_run

REPORT_FILE = "report.html"

MAX_REPORT_BYTES = 5 * 1024 * 1024
"""The size the report stays under (issue 17): plots are re-encoded smaller when one is larger than needed."""


def render_report(run_dir) -> str:
    """The report of ``run_dir`` as an HTML string (see :func:`write_report`); a ``torchcal fleet`` run directory
    gets the fleet report (:mod:`torchcal.report.fleet`)."""
    from . import model_sections as ms
    from . import sections as s
    from .fleet import is_fleet_run, render_fleet_report
    from .html import esc, page, section

    if is_fleet_run(run_dir):
        return render_fleet_report(run_dir)
    run: RunFiles = read_run(run_dir)
    robot = get(run.config, "robot", default=run.folder.name)
    parts = [
        section("summary", "Summary", s.summary(run), major=True, first=True),
        section("instrument", "Robot, instrument and noise model", s.instrument(run)),
        section("data", "Measurement data", s.data_summary(run)),
        section("checks", "Data checks and warnings", s.data_checks(run)),
        section("accuracy", "Accuracy before and after calibration", s.accuracy(run), major=True),
        section("histograms", "Residual histograms", s.distributions(run)),
        section("plots", "Plots", s.plots(run), major=True),
        section("parameters", "Identified parameters", ms.parameters(run), major=True),
        section("solver", "Identification", ms.solver(run)),
        section("compensation", "Compensation", ms.compensation(run), major=True),
        section("versions", "Versions and configuration", ms.appendix(run), major=True),
    ]
    footer = (f"Written by torchcal from the files of {esc(run.folder)}; this page is self-contained "
              "(no network, no script).")
    return page(f"Calibration report — {robot} — {run.folder.name}", s.title_block(run), parts, footer)


def write_report(run_dir, out=None) -> Path:
    """Write the calibration report of a run directory; returns its path.

    run_dir: a folder written by ``torchcal fit``, ``torchcal update`` or ``torchcal fleet`` (the fleet report);
    out: the HTML file to write (default ``<run_dir>/report.html``), replaced
    atomically (a failed write leaves an earlier report intact).

    Raises :class:`ReportError` (a ``TorchcalError``) naming the folder when
    ``run_dir`` is not a run directory, :class:`torchcal.io.atomic.WriteError`
    when the file cannot be written. Missing or unreadable files of the run
    only make their sections say "not available".
    """
    from ..io.atomic import atomic_write_text

    text = render_report(run_dir)
    path = Path(out) if out is not None else Path(run_dir) / REPORT_FILE
    return atomic_write_text(path, text)


__all__ = ["MAX_REPORT_BYTES", "Missing", "REPORT_FILE", "ReportError", "read_run", "render_report", "write_report"]
