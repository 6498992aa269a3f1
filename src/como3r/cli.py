"""The ``como3r`` command (manual: docs/commands/index.md).

Each command is a thin shell around one library function: it parses options, shows
progress, prints a summary table, and turns every :class:`~como3r.errors.Como3rError` into one
``error:`` line on stderr and exit status 2.
"""

from __future__ import annotations

import atexit
import gc
import logging
import os
from pathlib import Path

import typer

from como3r import cli_network, cli_results, cli_sessions
from como3r.cli_checks import (
    FORMAT_HELP,
    camera_sources,
    check_device,
    check_format,
    check_input,
    check_resumable,
    config_from_options,
    print_summary,
)
from como3r.cli_common import (
    Command,
    OneLineErrorsGroup,
    console,
    interrupt_keeps_the_store,
    interrupt_leaves_nothing,
    print_rows,
    user_errors,
)
from como3r.cli_progress import QUIET_HELP, run_progress
from como3r.cli_team import team_app
from como3r.cli_viewer import VIEWER_HELP, ViewerCommand, check_viewer_option, live_viewer
from como3r.cli_weights import weights_app
from como3r.errors import InputError

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
        help="Simulated robot odometry written as odometry.txt, its kind declared in "
        "odometry.json (decentralized mode): vio (declared vio), lio (declared metric) or none.",
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


app.command("eval", cls=Command)(cli_results.evaluate)
app.command("export", cls=Command)(cli_results.export)


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
    check_device(device)
    if prior not in PRIORS:
        raise InputError(f"unknown --prior {prior!r}; choose one of {', '.join(PRIORS)}")
    if precision not in PRECISIONS:  # also where the simulated prior would ignore it
        raise InputError(
            f"unknown --precision {precision!r}; choose one of {', '.join(PRECISIONS)}"
        )
    if mode not in ("centralized", "decentralized"):
        raise InputError(f"unknown --mode {mode!r}; choose centralized or decentralized")
    if format is not None:
        check_format(format)
    sources = camera_sources(camera, max_frames, agent, prior, mode)
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
    config = config_from_options(config_file, overrides, calib, no_loop_closure, format, topic)
    if resume:
        check_resumable(out, config)
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
        check_input(path, config, prior, every_pose=mode == "decentralized") for path in agent
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
        print_summary(summary, out)
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
        print_summary(summary, out)


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
    # The objects still alive at the exit are the interpreter's to free: its collections on
    # the way out walked torch's 300,000 (0.2 s each) and a command that had imported it took
    # 1.0-1.4 s of CPU to exit (0.15-0.2 s frozen). Explicit clean-ups (atexit, with) still run.
    atexit.register(gc.freeze)
    app()


if __name__ == "__main__":
    main()
