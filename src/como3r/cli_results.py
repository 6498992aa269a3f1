"""The commands that read a finished run: ``como3r eval`` (ATE and RPE against ground truth,
and the run's report) and ``como3r export`` (COLMAP, nerfstudio, g2o, depth maps, a ROS 2
bag). :mod:`como3r.cli` registers them.
"""

from __future__ import annotations

from pathlib import Path

import typer

from como3r.cli_checks import FORMAT_HELP, check_format
from como3r.cli_common import console, on_interrupt, print_rows, user_errors
from como3r.cli_progress import QUIET_HELP, run_progress
from como3r.errors import InputError


@on_interrupt(
    lambda kwargs: (
        "interrupted: nothing was written to "
        f"{kwargs['out'] if kwargs['out'] is not None else kwargs['est']}"
    )
)
@user_errors
def evaluate(
    est: Path = typer.Option(..., "--est", help="Run output folder (trajectories/agent_<a>.txt)."),
    gt: list[Path] = typer.Option(
        ...,
        "--gt",
        metavar="PATH",
        help="Ground truth per agent: TUM file, agent folder, TUM "
        "RGB-D or 7-Scenes sequence (repeat per agent).",
    ),
    out: Path | None = typer.Option(
        None,
        "--out",
        help="Where to write ate.json, the plot and report.html (default: the --est folder).",
    ),
    report: Path | None = typer.Option(
        None,
        "--report",
        metavar="PATH",
        help="Where to write report.html, the run's report with this evaluation (default: "
        "report.html in the --out folder; a run's own report there is replaced). "
        "Needs a run folder as --est.",
    ),
    format: str = typer.Option("auto", "--format", help=FORMAT_HELP),
) -> None:
    """ATE (and RPE) per agent and merged, through evo, and the run's report.html."""
    from como3r.evaluation.html import REPORT_NAME, write_evaluation_report
    from como3r.evaluation.report import evaluate_run

    check_format(format)
    folder = out if out is not None else est
    page = report if report is not None else folder / REPORT_NAME
    if report is not None and est.is_file():
        raise InputError(f"--report: {est} is a trajectory file; the report needs a run folder")
    if report is not None and report.is_dir():
        raise InputError(f"--report {report}: is a folder; give the page's file name")
    summary = evaluate_run(est, gt, folder, gt_format=format, check_gt_order=True)
    print_rows("ATE RMSE [m] (Sim(3)-aligned)", summary.table_rows())
    for line in summary.notes:
        console.print(line)
    if est.is_dir():
        try:
            page.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise InputError(
                f"--report {page}: cannot create its folder ({exc.strerror})"
            ) from None
        console.print(f"wrote {write_evaluation_report(est, summary, page)}")


@on_interrupt(lambda kwargs: "interrupted: no export was written")
@user_errors
def export(
    run: Path = typer.Argument(
        ..., metavar="RUN", show_default=False, help="A finished run folder (como3r run --out)."
    ),
    colmap: Path | None = typer.Option(
        None,
        "--colmap",
        metavar="DIR",
        help="COLMAP text model: DIR/sparse/0/*.txt and DIR/images.",
    ),
    nerfstudio: Path | None = typer.Option(
        None,
        "--nerfstudio",
        metavar="DIR",
        help="nerfstudio: DIR/transforms.json, images, depth, sparse_pc.ply.",
    ),
    g2o: Path | None = typer.Option(
        None, "--g2o", metavar="FILE", help="Keyframe pose graph (VERTEX_SE3:QUAT, EDGE_SE3:QUAT)."
    ),
    depth: Path | None = typer.Option(
        None,
        "--depth",
        metavar="DIR",
        help="Per keyframe depth and confidence (.npz) and 16-bit PNG depth (1000 per unit).",
    ),
    ros2_bag: Path | None = typer.Option(
        None,
        "--ros2-bag",
        metavar="DIR",
        help="ROS 2 bag (MCAP): /tf, per agent odometry, keyframe path, images and camera "
        "info, the map as PointCloud2.",
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace earlier exports of como3r."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help=QUIET_HELP),
) -> None:
    """Export a finished run to COLMAP, nerfstudio, g2o, depth maps and a ROS 2 bag (any
    subset)."""
    from como3r.io.export import export_run

    with run_progress(quiet) as shown:
        summary = export_run(
            run,
            colmap=colmap,
            nerfstudio=nerfstudio,
            g2o=g2o,
            depth=depth,
            ros2_bag=ros2_bag,
            overwrite=overwrite,
            progress=shown.steps("exporting keyframes"),
        )
    print_rows("exports", summary.rows)
    for line in summary.notes:
        console.print(line)
