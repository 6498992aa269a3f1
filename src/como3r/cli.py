"""The ``como3r`` command (README, "Commands").

Each command is a thin shell around one library function: it parses options, shows
progress, prints a summary table, and turns every :class:`Como3rError` into one
``error:`` line on stderr and exit status 2.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from como3r import cli_network, cli_sessions
from como3r.cli_common import (
    Command,
    OneLineErrorsGroup,
    console,
    interrupt_keeps_the_store,
    interrupt_leaves_nothing,
    on_interrupt,
    print_rows,
    user_errors,
)
from como3r.cli_progress import QUIET_HELP, run_progress
from como3r.cli_team import team_app
from como3r.cli_viewer import VIEWER_HELP, ViewerCommand, check_viewer_option, live_viewer
from como3r.cli_weights import weights_app
from como3r.errors import InputError

if TYPE_CHECKING:
    from como3r.data.readers.camera import CameraSource

app = typer.Typer(
    cls=OneLineErrorsGroup,
    add_completion=False,
    no_args_is_help=True,
    help="Collaborative monocular dense SLAM with a learned two-view 3D prior.",
)
app.add_typer(weights_app, name="weights")
app.add_typer(team_app, name="team")


@app.callback()
def _main(verbose: bool = typer.Option(False, "--verbose", "-v", help="Debug logging.")) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )


@app.command(cls=Command)
@interrupt_leaves_nothing
@user_errors
def synth(
    out: Path = typer.Option(..., "--out", help="Folder to write the scene to."),
    agents: int = typer.Option(2, "--agents", min=1, help="Number of agents."),
    seed: int = typer.Option(0, "--seed", help="Random seed."),
    overlap: float = typer.Option(
        0.2, "--overlap", min=0.0, max=1.0, help="Fraction of each path shared with a neighbour."
    ),
    frames: int = typer.Option(100, "--frames", min=2, help="Frames per agent."),
    preset: str = typer.Option(
        "default",
        "--preset",
        help="default | aliasing | no-meeting | forward | rotation | "
        "fast | low-texture | covered | revisit",
    ),
    width: int = typer.Option(320, "--width", min=16),
    height: int = typer.Option(240, "--height", min=16),
    scale: float = typer.Option(
        1.0,
        "--scale",
        help="Multiply the whole scene and paths (0.1 tabletop, 1 rooms, 5 street, 20 aerial).",
    ),
    loop_frames: int | None = typer.Option(
        None,
        "--loop-frames",
        help="Lay the loop out for at least this many frames per agent (default: --frames): "
        "short paths then turn as little per frame as long ones.",
    ),
    odometry: str = typer.Option(
        "vio",
        "--odometry",
        help="Simulated robot odometry written as odometry.txt "
        "(decentralized mode): vio, lio or none.",
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing folder."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help=QUIET_HELP),
) -> None:
    """Synthesize a multi-agent outdoor scene with ground truth."""
    from como3r.data.synth import PRESETS, synthesize
    from como3r.decentralized.odometry_sim import ODOMETRY_PRESETS, add_odometry
    from como3r.io.output import atomic_output_dir

    if preset not in PRESETS:  # before the progress bar
        raise InputError(f"--preset: unknown preset {preset!r} (valid: {', '.join(PRESETS)})")
    if odometry != "none" and odometry not in ODOMETRY_PRESETS:
        raise InputError(
            f"unknown --odometry {odometry!r}; choose none or one of "
            f"{', '.join(sorted(ODOMETRY_PRESETS))}"
        )
    with atomic_output_dir(out, overwrite=overwrite) as staging, run_progress(quiet) as shown:
        synthesize(
            staging,
            agents=agents,
            seed=seed,
            overlap=overlap,
            frames=frames,
            preset=preset,
            width=width,
            height=height,
            scale=scale,
            loop_frames=loop_frames,
            progress=shown.counter("rendering", agents * frames),
        )
        if odometry != "none":
            for a in range(agents):
                add_odometry(staging / f"agent_{a}", seed=seed * 1000 + a, params=odometry)
    console.print(f"wrote {agents} agent folder(s) to {out}")


@app.command(cls=Command)
@interrupt_leaves_nothing
@user_errors
def split(
    sequence: Path = typer.Argument(
        ...,
        metavar="SEQ",
        show_default=False,
        help="One sequence: a dataset folder, an agent folder, a "
        "video or a ROS log (layout detected).",
    ),
    out: Path = typer.Option(..., "--out", help="Folder to write agent_0 ... agent_<K-1> to."),
    agents: int = typer.Option(..., "--agents", min=1, help="Number of agents K."),
    overlap: float = typer.Option(
        0.05,
        "--overlap",
        min=0.0,
        max=0.99,
        help="Fraction of each agent's frames shared with the next "
        "agent (CoMo3R's protocol: a short shared segment).",
    ),
    stride: int = typer.Option(
        1, "--stride", min=1, help="Keep every N-th frame of the sequence before splitting."
    ),
    format: str = typer.Option("auto", "--format", help="Layout of SEQ (see run --format)."),
    topic: str = typer.Option("", "--topic", help="A ROS log's image topic."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing folder."),
) -> None:
    """Split one sequence into K overlapping agent inputs, as the CoMo3R paper does."""
    from como3r.data.split import split_sequence
    from como3r.io.output import atomic_output_dir

    with atomic_output_dir(out, overwrite=overwrite) as staging:
        folders = split_sequence(
            sequence,
            staging,
            agents=agents,
            overlap=overlap,
            stride=stride,
            topic=topic,
            format=format,
        )
    console.print(
        f"wrote {len(folders)} agent folder(s) to {out}: "
        + " ".join(f"{out / f.name}" for f in folders)
    )


FORMAT_HELP = (
    "Layout of the input folders: auto (detect) | agent | tum (TUM RGB-D) | "
    "7scenes | euroc (EuRoC MAV) | kitti (KITTI odometry) | tanks (Tanks and "
    "Temples) | rosbag (ROS 1 .bag, ROS 2 bag folder)."
)


@app.command("eval", cls=Command)
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

    _check_format(format)
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


@app.command("export", cls=Command)
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


def _load_config(
    config_file: Path | None,
    overrides: list[str],
    calib: bool,
    no_loop_closure: bool,
    format: str | None = None,
    topic: str | None = None,
):
    import dataclasses

    from como3r.config import Config, apply_overrides, load_config

    config = load_config(config_file) if config_file is not None else Config()
    extra = (["calibrated=true"] if calib else []) + (
        ["loop_closure=false"] if no_loop_closure else []
    )
    if format is not None:
        extra.append(f"input.format={format}")
    config = apply_overrides(config, [*overrides, *extra])
    if topic is not None:  # as given: a topic is any string, not a YAML scalar
        config = dataclasses.replace(config, input=dataclasses.replace(config.input, topic=topic))
    return config


@app.command(cls=ViewerCommand)
@interrupt_keeps_the_store
@user_errors
def run(
    agent: list[Path] = typer.Option(
        [],
        "--agent",
        metavar="PATH",
        help="Agent input: agent folder, video, dataset "
        "sequence folder or ROS log (repeat per agent).",
    ),
    camera: list[str] = typer.Option(
        [],
        "--camera",
        metavar="SOURCE",
        help="Live agent input instead of --agent: a camera's device index (0), a stream URL "
        "(rtsp://..., http://...) or a video file played as if live (repeat per agent). "
        "Runs in this process; frames arriving while SLAM is busy are dropped (the "
        "newest is kept) and counted. Ends at the end of the stream, after "
        "--max-frames, or on Ctrl-C (the outputs are written; twice: abort).",
    ),
    max_frames: int | None = typer.Option(
        None, "--max-frames", metavar="N", help="End each --camera stream after N frames."
    ),
    format: str | None = typer.Option(
        None, "--format", help=FORMAT_HELP + " Default: the configuration's input.format (auto)."
    ),
    topic: str | None = typer.Option(
        None,
        "--topic",
        metavar="NAME",
        help="Image topic of the ROS log inputs (default: the configuration's input.topic; "
        "empty: each log's only image topic).",
    ),
    out: Path | None = typer.Option(  # checked after the input, which a user gives first
        None, "--out", help="Output folder (required)."
    ),
    prior: str = typer.Option(
        "mast3r",
        "--prior",
        help="mast3r | simulated (a stand-in built from the input's depth and ground-truth "
        "poses, for synthetic scenes and RGB-D datasets with ground truth; it does not "
        "measure MASt3R).",
    ),
    weights: Path | None = typer.Option(
        None,
        "--weights",
        help="MASt3R checkpoint (default: the weights cache, filled by `como3r weights fetch`).",
    ),
    retrieval_weights: Path | None = typer.Option(
        None,
        "--retrieval-weights",
        help="MASt3R retrieval checkpoint (default: the weights "
        "cache when --weights is not given).",
    ),
    codebook: Path | None = typer.Option(
        None,
        "--codebook",
        help="ASMK codebook .pkl (default: beside the retrieval "
        "checkpoint, else the weights cache).",
    ),
    config_file: Path | None = typer.Option(None, "--config", help="YAML configuration."),
    overrides: list[str] = typer.Option(
        [], "--set", metavar="KEY=VALUE", help="Override, e.g. tracking.sigma_ray=0.002 (repeat)."
    ),
    calib: bool = typer.Option(False, "--calib", help="Use each agent's calib.txt (C-Sec. A.5)."),
    no_loop_closure: bool = typer.Option(False, "--no-loop-closure", help="Ablation (C-Tab. 4)."),
    device: str = typer.Option("cpu", "--device", help="cpu | cuda"),
    precision: str = typer.Option(
        "auto",
        "--precision",
        help="MASt3R compute precision: auto | fp32 | bf16 | fp16. auto takes bf16 on CUDA "
        "compute capability >= 8.0 or a CPU with AMX/AVX512-BF16, else fp32; fp16 is "
        "CUDA-only. The simulated prior ignores it.",
    ),
    mode: str = typer.Option("centralized", "--mode", help="centralized | decentralized"),
    single_process: bool = typer.Option(
        False,
        "--single-process",
        help="Run agents and coordinator in this process (deterministic; for debugging).",
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing folder."),
    resume: bool = typer.Option(
        False,
        "--resume",
        help="Continue a run that was killed or interrupted (OUT.partial) from its session "
        "store: the same command with --resume. The agents start again from the "
        "beginning; the keyframes the store holds are not processed again.",
    ),
    map_folder: Path | None = typer.Option(
        None,
        "--map",
        metavar="DIR",
        help="Start on the map of a finished run (its output folder, made with the same "
        "configuration): its agents keep their ids and are in this run's outputs too, "
        "the new agents are numbered after them and join its frame where they see the "
        "same places.",
    ),
    freeze_map: bool = typer.Option(
        False,
        "--freeze-map",
        help="Hold the --map keyframes fixed (poses and depths): only the new agents move.",
    ),
    quiet: bool = typer.Option(False, "--quiet", "-q", help=QUIET_HELP),
    viewer: str | None = typer.Option(None, "--viewer", metavar="MODE", help=VIEWER_HELP),
) -> None:
    """Run collaborative SLAM on one or more agents and write the output folder."""
    from como3r.data.readers.camera import is_stream_url
    from como3r.io.output import check_output_dir
    from como3r.prior.mast3r.precision import PRECISIONS, check_precision
    from como3r.runtime.pipeline import PRIORS, PriorSpec, resolve_weights
    from como3r.runtime.pipeline import run as run_pipeline
    from como3r.store.reader import resumable

    # every option is checked before any work starts (and before a progress bar shows)
    _check_device(device)
    if prior not in PRIORS:
        raise InputError(f"unknown --prior {prior!r}; choose one of {', '.join(PRIORS)}")
    if precision not in PRECISIONS:  # also where the simulated prior would ignore it
        raise InputError(
            f"unknown --precision {precision!r}; choose one of {', '.join(PRECISIONS)}"
        )
    if mode not in ("centralized", "decentralized"):
        raise InputError(f"unknown --mode {mode!r}; choose centralized or decentralized")
    if format is not None:
        _check_format(format)
    sources = _camera_sources(camera, max_frames, agent, prior, mode)
    if out is None:
        raise InputError("missing option --out: the output folder (see: como3r run --help)")
    if viewer is not None and mode == "decentralized":
        raise InputError("--viewer shows --mode centralized runs only")
    viewer_spec = check_viewer_option(viewer, out)  # rerun installed?
    if resume and (mode == "decentralized" or sources):
        raise InputError("--resume continues --mode centralized runs of recorded inputs only")
    if freeze_map and map_folder is None:
        raise InputError("--freeze-map holds the keyframes of a --map fixed; give --map DIR")
    if map_folder is not None and mode == "decentralized":
        raise InputError("--map starts a --mode centralized run on a saved map")
    check_output_dir(
        out,
        overwrite,
        resume,  # before the weights load and the agents start
        resumable if mode == "centralized" and not sources else None,
    )
    config = _load_config(config_file, overrides, calib, no_loop_closure, format, topic)
    if resume:
        _check_resumable(out, config)
    saved_map = None
    if map_folder is not None:
        from como3r.runtime.map_session import open_map

        saved_map = open_map(map_folder, config, freeze_map)
    for path in agent:
        if not path.exists():
            hint = " (a stream URL goes to --camera)" if is_stream_url(str(path)) else ""
            raise InputError(f"{path}: agent input does not exist{hint}")
    # input problems before weights are looked for
    simulatable = [
        _check_input(path, config, prior, every_pose=mode == "decentralized") for path in agent
    ]
    spec = PriorSpec(prior, weights, retrieval_weights, codebook, device, precision)
    if prior == "mast3r":
        check_precision(device, precision)
        try:
            spec = resolve_weights(spec)
        except InputError as exc:
            if not (simulatable and all(simulatable)):
                raise
            raise InputError(
                f"{exc}. These inputs have metric depth and ground-truth poses: "
                "they also run with --prior simulated, a stand-in built from "
                "them that does not measure MASt3R"
            ) from None
        for option, path in (
            ("--weights", spec.weights),
            ("--retrieval-weights", spec.retrieval_weights),
            ("--codebook", spec.codebook),
        ):
            if path is not None and not path.is_file():
                raise InputError(f"{option} {path}: no such file")
    if mode == "decentralized":
        from como3r.decentralized.runner import run_decentralized

        with run_progress(quiet) as shown:
            summary = run_decentralized(
                agent, out, config, spec, overwrite=overwrite, progress=shown
            )
        _print_summary(summary, out)
        return
    if single_process or sources:  # live inputs run in this process
        runner = run_pipeline
    else:
        from como3r.runtime.multiprocess import run_multiprocess as runner
    with live_viewer(viewer_spec) as live:
        with run_progress(quiet) as shown:
            summary = runner(
                agent or sources,
                out,
                config,
                spec,
                overwrite=overwrite,
                progress=shown,
                live=live,
                resume=resume,
                saved_map=saved_map,
            )
        _print_summary(summary, out)


def _check_resumable(out: Path, config) -> None:
    """The killed run in ``out.partial`` has a session store made with ``config``."""
    from como3r.config import differing_key
    from como3r.store.reader import read_config
    from como3r.store.schema import STORE_NAME

    store = out.with_name(out.name + ".partial") / STORE_NAME
    difference = differing_key(read_config(store), config)
    if difference is not None:
        raise InputError(
            f"--resume: the configuration differs from the stored session's "
            f"({difference}); give the options of the run that was killed"
        )


def _check_format(format: str) -> None:
    """``--format`` names a known input layout (:data:`como3r.data.readers.FORMATS`)."""
    from como3r.data.readers import FORMATS

    if format not in FORMATS:
        raise InputError(f"unknown --format {format!r}; choose one of {', '.join(FORMATS)}")


def _camera_sources(
    camera: list[str], max_frames: int | None, agent: list[Path], prior: str, mode: str
) -> list[CameraSource]:
    """The :class:`~como3r.data.readers.camera.CameraSource` of each ``--camera``, after
    the checks of what a live input cannot do.

    Raises:
        InputError: no input at all, --camera beside --agent, --max-frames without
            --camera, or a live input with the simulated prior or the decentralized mode.
    """
    from como3r.data.readers.camera import parse_source

    if not camera:
        if not agent:
            raise InputError(
                "no input: give --agent PATH or --camera SOURCE (see: como3r run --help)"
            )
        if max_frames is not None:
            raise InputError("--max-frames ends --camera streams; there is none")
        return []
    if agent:
        raise InputError("a run takes recorded inputs (--agent) or live ones (--camera), not both")
    if prior == "simulated":
        raise InputError(
            "--camera: a live camera has no depth, which --prior simulated needs "
            "(a stand-in made from ground-truth depth); use --prior mast3r"
        )
    if mode == "decentralized":
        raise InputError(
            "--camera: --mode decentralized needs each robot's odometry "
            "(odometry.txt), which a live camera does not give"
        )
    return [parse_source(text, max_frames) for text in camera]


def _check_input(path: Path, config, prior: str, every_pose: bool = False) -> bool:
    """An input opened before any work and before MASt3R's weights are looked for (its
    layout, files and image headers: :func:`como3r.data.agent.open_agent`), and what
    ``--prior simulated`` needs of it: depth, intrinsics and ground-truth poses (or
    appearance keys); frames without a pose (before the first, after the last, in a gap
    wider than :data:`como3r.data.poses.MAX_GAP`) are skipped by the run, with one warning,
    so at least one frame must have one; ``every_pose``: every frame must (decentralized
    robots pick their keyframes by odometry and do not skip frames).

    Returns:
        Whether ``--prior simulated`` could run the input (depth, intrinsics, and appearance
        keys or a ground-truth pose for some frame).

    Raises:
        InputError: naming the input and what is wrong with it or what it lacks; images
            alone take --prior mast3r.
    """
    from como3r.data.agent import open_agent, quiet_reading
    from como3r.data.poses import MAX_GAP
    from como3r.data.readers import DEPTH_SOURCES

    with quiet_reading():  # the run opens it again and says the readers' warnings once
        source = open_agent(
            path,
            fps=config.input.frame_rate_hz,
            format=config.input.format,
            topic=config.input.topic,
        )
    if prior != "simulated":
        return bool(
            source.has_depth
            and source.calib is not None
            and (
                source.has_surface or (source.groundtruth is not None and source.has_gt_pose.any())
            )
        )
    needs = (
        "which --prior simulated needs (a stand-in made from ground-truth depth); "
        "images alone take --prior mast3r"
    )
    if not source.has_depth:
        raise InputError(f"{path}: no {DEPTH_SOURCES[source.format]}, {needs}")
    if source.calib is None:
        raise InputError(f"{path}: no intrinsics (calib.txt 'fx fy cx cy'), {needs}")
    if not source.has_surface:
        if source.groundtruth is None:
            raise InputError(f"{path}: no ground truth, {needs}")
        has = source.has_gt_pose
        if not has.any():
            raise InputError(
                f"{path}: no frame has a ground-truth pose within {MAX_GAP:g} s, {needs}"
            )
        if every_pose and not has.all():
            raise InputError(
                f"{path}: {int((~has).sum())} of {source.num_frames} frames have "
                f"no ground-truth pose within {MAX_GAP:g} s, which --prior "
                "simulated needs for every frame in --mode decentralized"
            )
    return True


def _check_device(device: str) -> None:
    """``--device`` is cpu, cuda or cuda:N, and CUDA only where this torch can use it.

    Raises:
        InputError: another device, or CUDA that torch cannot reach (no silent CPU run).
    """
    if device == "cpu":
        return
    match = re.fullmatch(r"cuda(?::(\d+))?", device)
    if match is None:
        raise InputError(f"unknown --device {device!r}; choose cpu or cuda")
    import torch

    if not torch.cuda.is_available():
        why = (
            f"this torch ({torch.__version__}) is built without CUDA"
            if torch.version.cuda is None
            else "torch finds no usable CUDA device"
        )
        raise InputError(f"--device {device}: {why}; use --device cpu")
    count = torch.cuda.device_count()
    if int(match.group(1) or 0) >= count:
        raise InputError(f"--device {device}: this machine has {count} CUDA device(s)")


def _print_summary(summary, out: Path) -> None:
    """The final tables of a run."""
    print_rows("agents", summary.agents)
    if summary.evaluation is not None:
        print_rows("ATE RMSE [m] (Sim(3)-aligned)", summary.evaluation.table_rows())
    for line in summary.notes:
        console.print(line)
    console.print(f"wrote {out}")


#: the demo renders what a camera gives (640x480) and runs it at the default long side 512
DEMO_SIZE = (640, 480)
#: the demo's loop is laid out for this many frames per agent, so a short demo turns at a
#: hand-held pace (3.6 deg per frame) instead of spinning round its whole loop
DEMO_LOOP_FRAMES = 100


@app.command(cls=ViewerCommand)
@interrupt_leaves_nothing
@user_errors
def demo(
    agents: int = typer.Option(2, "--agents", min=1, help="Number of agents."),
    out: Path = typer.Option(Path("demo_out"), "--out", help="Output folder."),
    frames: int = typer.Option(30, "--frames", min=4, help="Frames per agent."),
    seed: int = typer.Option(0, "--seed", help="Random seed of the scene."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing folder."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help=QUIET_HELP),
    viewer: str | None = typer.Option(None, "--viewer", metavar="MODE", help=VIEWER_HELP),
) -> None:
    """Synthesize a scene, run collaborative SLAM with the simulated prior, evaluate, report."""
    from como3r.config import Config
    from como3r.data.synth import synthesize
    from como3r.io.output import atomic_output_dir
    from como3r.runtime.multiprocess import run_multiprocess
    from como3r.runtime.pipeline import PriorSpec

    width, height = DEMO_SIZE
    scene = out / "scene"
    viewer_spec = check_viewer_option(viewer, out)  # rerun installed?
    with live_viewer(viewer_spec) as live:
        with atomic_output_dir(out, overwrite=overwrite) as staging, run_progress(quiet) as shown:
            (staging / "scene").mkdir()
            synthesize(
                staging / "scene",
                agents=agents,
                seed=seed,
                overlap=0.2,
                frames=frames,
                preset="default",
                width=width,
                height=height,
                loop_frames=max(frames, DEMO_LOOP_FRAMES),
                progress=shown.counter("rendering", agents * frames),
            )
            config = Config()  # the defaults, nothing overridden: what a user gets
            # one process per agent and the coordinator here, as `como3r run` does by default
            summary = run_multiprocess(
                [staging / "scene" / f"agent_{a}" for a in range(agents)],
                staging / "run",
                config,
                PriorSpec("simulated"),
                progress=shown,
                live=live,
            )
            accuracy = summary.evaluation.table_rows() if summary.evaluation is not None else []
        print_rows("agents", summary.agents)
        if accuracy:
            print_rows("ATE RMSE [m] (Sim(3)-aligned)", accuracy)
        for line in summary.notes:
            console.print(line)
        console.print(f"scene: {scene}\nrun:   {out / 'run'} (open {out / 'run' / 'report.html'})")


app.command("merge", cls=Command)(cli_sessions.merge)
app.command("coordinator", cls=Command)(cli_network.coordinator)
app.command("agent", cls=Command)(cli_network.agent)
app.command("robot", cls=Command)(cli_network.robot)


#: OpenMP threads that wait for work sleep instead of spinning. PyTorch's default (spinning
#: workers) lets one process's idle threads take the cores another needs: on a 2-core machine
#: shared with other work, a focal-length estimate took 17.4 s with two threads against 1.9 s
#: with one, and 1.5 s with two under this policy. Read once, when torch loads OpenMP: set
#: before any command imports it (child processes inherit it); a user's own setting is kept.
OMP_WAIT_POLICY = "PASSIVE"


def main() -> None:
    """Entry point of the console script."""
    os.environ.setdefault("OMP_WAIT_POLICY", OMP_WAIT_POLICY)
    app()


if __name__ == "__main__":
    main()
