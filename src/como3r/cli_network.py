"""``como3r coordinator``, ``como3r agent`` and ``como3r robot``: runs across machines over
Zenoh (:mod:`como3r.runtime.network`, :mod:`como3r.decentralized.robot_node`; manual:
docs/networked.md)."""

from __future__ import annotations

import dataclasses
import functools
import inspect
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, TypeVar

import typer

from como3r.cli_checks import check_device, check_resumable, config_from_options, print_summary
from como3r.cli_common import (
    console,
    err_console,
    interrupt_keeps_the_store,
    interrupt_leaves_nothing,
    on_interrupt,
    user_errors,
)
from como3r.cli_progress import QUIET_HELP, run_progress
from como3r.errors import InputError

DEFAULT_PORT = 7447

PRIOR_HELP = (
    "mast3r | simulated (a stand-in built from the input's depth and ground-truth "
    "poses, for synthetic scenes and RGB-D datasets with ground truth; it does not "
    "measure MASt3R). The same on every process of the run."
)

# ------------------------------------------------------------ options the commands share

ListenOption = Annotated[
    list[str],
    typer.Option(
        "--listen",
        metavar="ENDPOINT",
        help="Zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeat for several).",
    ),
]
ConnectOption = Annotated[
    list[str],
    typer.Option(
        "--connect",
        metavar="ENDPOINT",
        help=f"Zenoh endpoint to connect to, e.g. tcp/HOST:{DEFAULT_PORT} (repeat).",
    ),
]
PriorOption = Annotated[str, typer.Option("--prior", help=PRIOR_HELP)]
WeightsOption = Annotated[Path | None, typer.Option("--weights", help="MASt3R checkpoint.")]
RetrievalOption = Annotated[
    Path | None, typer.Option("--retrieval-weights", help="MASt3R retrieval checkpoint.")
]
CodebookOption = Annotated[Path | None, typer.Option("--codebook", help="ASMK codebook .pkl.")]
DeviceOption = Annotated[str, typer.Option("--device", help="cpu | cuda")]
PrecisionOption = Annotated[str, typer.Option("--precision", help="auto | fp32 | bf16 | fp16")]
ConfigOption = Annotated[
    Path | None,
    typer.Option("--config", help="YAML configuration (the same on every process that reads one)."),
]
SetOption = Annotated[
    list[str],
    typer.Option("--set", metavar="KEY=VALUE", help="Override, e.g. tracking.sigma_ray=0.002."),
]
CalibOption = Annotated[bool, typer.Option("--calib", help="Use each input's calib.txt.")]
SessionOption = Annotated[
    str,
    typer.Option(
        "--session",
        help="Name of the run in the Zenoh key expressions (several runs on one network).",
    ),
]
ScoutingOption = Annotated[
    bool,
    typer.Option(
        "--scouting",
        help="Find peers by UDP multicast on the local network too (off: only the "
        "given endpoints).",
    ),
]
ZenohConfigOption = Annotated[
    Path | None,
    typer.Option(
        "--zenoh-config",
        metavar="FILE",
        help="Zenoh configuration file (JSON5) to start from: TLS, authentication, access "
        "control as Zenoh documents them; the options here are set on top of it.",
    ),
]
TeamOption = Annotated[
    Path | None,
    typer.Option(
        "--team",
        metavar="TEAM/NAME",
        help="This machine's member folder (como3r team add): speak only mutual TLS with the "
        "team's certificates, under access control from them (tcp/ endpoints are taken "
        "as tls/). Without it the network is open to anyone who can reach it.",
    ),
]
MaxMbpsOption = Annotated[
    float,
    typer.Option(
        "--max-mbps",
        min=0.0,
        metavar="M",
        help="Rate limit of what this process sends, Mbit/s (its radio link; 0: none): "
        "small messages (acknowledgements, pose updates) go before large ones.",
    ),
]
OutOption = Annotated[Path, typer.Option("--out", help="Output folder.")]
OverwriteOption = Annotated[bool, typer.Option("--overwrite", help="Replace an existing folder.")]
QuietOption = Annotated[bool, typer.Option("--quiet", "-q", help=QUIET_HELP)]
InputArgument = Annotated[
    Path,
    typer.Argument(
        metavar="PATH", show_default=False, help="This process's input (as como3r run --agent)."
    ),
]


#: the one line a networked command prints without --team
OPEN_NETWORK = (
    "warning: open network: anyone who can reach these endpoints can join this "
    "run and write into its map (make a team: como3r team init / add, then --team)"
)


def _network(
    listen: list[str],
    connect: list[str],
    scouting: bool,
    zenoh_config: Path | None,
    session: str,
    team: Path | None = None,
    role: str = "",
    member_id: int | None = None,
    peers: int | None = None,
):
    """The Zenoh options of a networked command: a team member's (``team``: its folder,
    checked to hold a certificate of ``role`` and ``member_id``; ``peers`` agents or robots)
    or, with one warning line, an open network's."""
    from como3r.transport.team import check_role, load_member
    from como3r.transport.team_access import network_options
    from como3r.transport.zenoh_protocol import ZenohOptions

    if zenoh_config is not None and not zenoh_config.is_file():
        raise InputError(f"--zenoh-config {zenoh_config}: no such file")
    if team is None:
        err_console.print(OPEN_NETWORK, style="yellow", highlight=False, soft_wrap=True)
        return ZenohOptions(tuple(listen), tuple(connect), scouting, zenoh_config, session)
    member = load_member(team)
    check_role(member, role, member_id)
    return network_options(member, listen, connect, scouting, zenoh_config, session, peers)


def _prior_spec(
    prior: str,
    weights: Path | None,
    retrieval_weights: Path | None,
    codebook: Path | None,
    device: str,
    precision: str,
):
    from como3r.prior.mast3r.precision import PRECISIONS, check_precision
    from como3r.runtime.pipeline import PRIORS, PriorSpec, resolve_weights

    check_device(device)
    if prior not in PRIORS:
        raise InputError(f"unknown --prior {prior!r}; choose one of {', '.join(PRIORS)}")
    if precision not in PRECISIONS:
        raise InputError(
            f"unknown --precision {precision!r}; choose one of {', '.join(PRECISIONS)}"
        )
    spec = PriorSpec(prior, weights, retrieval_weights, codebook, device, precision)
    if prior == "mast3r":
        check_precision(device, precision)
        spec = resolve_weights(spec)
    return spec


#: the options that choose the prior, as (parameter, annotated type, default)
PRIOR_PARAMETERS = (
    ("prior", PriorOption, "mast3r"),
    ("weights", WeightsOption, None),
    ("retrieval_weights", RetrievalOption, None),
    ("codebook", CodebookOption, None),
    ("device", DeviceOption, "cpu"),
    ("precision", PrecisionOption, "auto"),
)

F = TypeVar("F", bound=Callable[..., None])


def with_prior(command: F) -> F:
    """Give a command the options of :data:`PRIOR_PARAMETERS` in place of its ``prior_spec``
    parameter, which receives them checked as one
    :class:`~como3r.runtime.pipeline.PriorSpec` (bad values: an ``error:`` line through
    :func:`~como3r.cli_common.user_errors`, applied outside this decorator)."""
    parameters = []
    for parameter in inspect.signature(command, eval_str=True).parameters.values():
        if parameter.name == "prior_spec":
            parameters += [
                inspect.Parameter(
                    name, inspect.Parameter.KEYWORD_ONLY, default=default, annotation=annotation
                )
                for name, annotation, default in PRIOR_PARAMETERS
            ]
        else:
            parameters.append(parameter.replace(kind=inspect.Parameter.KEYWORD_ONLY))

    @functools.wraps(command)
    def wrapper(**kwargs: Any) -> None:
        spec = _prior_spec(*(kwargs.pop(name) for name, _, _ in PRIOR_PARAMETERS))
        command(prior_spec=spec, **kwargs)

    wrapper.__signature__ = inspect.Signature(parameters)  # type: ignore[attr-defined]
    wrapper.__annotations__ = {p.name: p.annotation for p in parameters}
    return wrapper  # type: ignore[return-value]


@interrupt_keeps_the_store
@user_errors
@with_prior
def coordinator(
    out: OutOption,
    listen: ListenOption = [f"tcp/0.0.0.0:{DEFAULT_PORT}"],
    connect: ConnectOption = [],
    agents: int = typer.Option(
        2, "--agents", min=1, help="Agents taking part, ids 0 to N-1 (como3r agent --id)."
    ),
    gt: list[Path] = typer.Option(
        [],
        "--gt",
        metavar="PATH",
        help="Ground truth per agent to evaluate against, as "
        "como3r eval --gt (repeat per agent, in id order).",
    ),
    prior_spec: Any = None,
    config_file: ConfigOption = None,
    overrides: SetOption = [],
    calib: CalibOption = False,
    no_loop_closure: bool = typer.Option(False, "--no-loop-closure", help="Ablation."),
    agent_timeout: float = typer.Option(
        900.0,
        "--agent-timeout",
        metavar="SECONDS",
        min=0.1,
        help="An agent silent for longer (or that never joins) counts as failed.",
    ),
    away_timeout: float = typer.Option(
        120.0,
        "--away-timeout",
        metavar="SECONDS",
        min=0.0,
        help="An agent whose link is lost (crash, Wi-Fi gap) is away, not failed, for this "
        "long: it may reconnect, or be restarted with its --id (0: failed at once). With the "
        "outputs written, the coordinator also waits up to this long for an agent that may "
        "not have its last acknowledgement.",
    ),
    max_message_mb: float = typer.Option(
        256.0,
        "--max-message-mb",
        min=0.001,
        help="Size cap of one message; larger ones are dropped.",
    ),
    session: SessionOption = "como3r",
    scouting: ScoutingOption = False,
    zenoh_config: ZenohConfigOption = None,
    team: TeamOption = None,
    max_mbps: MaxMbpsOption = 0.0,
    overwrite: OverwriteOption = False,
    resume: bool = typer.Option(
        False,
        "--resume",
        help="Continue a coordinator that was killed (OUT.partial) from its session store: "
        "the same command with --resume. Agents still running re-send what it had not "
        "stored; agents restarted meanwhile continue after the last frame it stored.",
    ),
    quiet: QuietOption = False,
) -> None:
    """Coordinate agents on other machines (como3r agent) over Zenoh.

    Writes the output folder once every agent has finished or failed."""
    import torch

    from como3r.io.output import check_output_dir
    from como3r.runtime.agent_events import RuntimeOptions
    from como3r.runtime.network import serve
    from como3r.store.reader import resumable

    network = _network(
        listen, connect, scouting, zenoh_config, session, team, "coordinator", peers=agents
    )
    network = dataclasses.replace(network, max_mbps=max_mbps)
    check_output_dir(
        out,
        overwrite,
        resume,  # a finished store resumes here too
        lambda staging: resumable(staging, finished=True),
    )
    config = config_from_options(config_file, overrides, calib, no_loop_closure)
    if resume:
        check_resumable(out, config)
    threads = torch.get_num_threads()  # this machine runs no agent
    options = RuntimeOptions(
        torch_threads=threads,
        max_message_bytes=int(max_message_mb * 2**20),
        agent_timeout_s=agent_timeout,
        away_timeout_s=away_timeout,
    )
    if not quiet:  # who starts the agents needs these endpoints and the session
        err_console.print(
            f"coordinator: waiting for {agents} agent(s) ({network.where()})",
            markup=False,
            highlight=False,
            soft_wrap=True,
        )
    with run_progress(quiet) as shown:
        summary = serve(
            network,
            agents,
            out,
            config,
            prior_spec,
            options,
            ground_truth=gt,
            overwrite=overwrite,
            progress=shown,
            resume=resume,
        )
    print_summary(summary, out)


@on_interrupt(lambda kwargs: f"interrupted: agent {kwargs['agent_id']} stopped")
@user_errors
@with_prior
def agent(
    path: InputArgument,
    agent_id: int = typer.Option(..., "--id", min=0, help="This agent's id (0 to N-1)."),
    connect: ConnectOption = [],
    listen: ListenOption = [],
    prior_spec: Any = None,
    threads: int | None = typer.Option(
        None, "--threads", min=1, help="Torch threads (default: torch's here)."
    ),
    queue_memory_mb: float = typer.Option(
        256.0,
        "--queue-memory-mb",
        min=0.0,
        help="Messages the coordinator has not stored yet (it is away, or slow) kept in "
        "memory; more are spilled to disk.",
    ),
    spill_dir: Path | None = typer.Option(
        None,
        "--spill-dir",
        metavar="DIR",
        help="Where to spill them (default: the system's temporary folder).",
    ),
    session: SessionOption = "como3r",
    scouting: ScoutingOption = False,
    zenoh_config: ZenohConfigOption = None,
    team: TeamOption = None,
    max_mbps: MaxMbpsOption = 0.0,
) -> None:
    """Track one camera for a coordinator on another machine (como3r coordinator).

    Keeps tracking while the coordinator is away and re-sends on its return; leaves once
    the coordinator has stored every message. Restarted with the same --id, it takes over
    after the last frame the coordinator heard of."""
    from como3r.runtime.network import run_remote_agent
    from como3r.transport.zenoh_agent import SendStatus

    if not connect and not scouting:
        raise InputError("give the coordinator's --connect tcp/HOST:PORT (or --scouting)")
    network = _network(listen, connect, scouting, zenoh_config, session, team, "agent", agent_id)
    network = dataclasses.replace(network, max_mbps=max_mbps)
    if spill_dir is not None and not spill_dir.is_dir():
        raise InputError(f"--spill-dir {spill_dir}: no such folder")
    said: list[SendStatus] = []

    def say(status: SendStatus) -> None:
        said.append(status)
        err_console.print(
            f"agent {agent_id}: {status.line()}", markup=False, highlight=False, soft_wrap=True
        )

    if not run_remote_agent(
        network,
        agent_id,
        path,
        prior_spec,
        threads,
        int(queue_memory_mb * 2**20),
        spill_dir,
        on_status=say if max_mbps > 0 else said.append,
    ):
        raise InputError(f"agent {agent_id} did not finish its input (see the log above)")
    peak = ""
    if said and said[-1].max_mbps is not None:
        last = said[-1]
        peak = f"; sent {last.bytes_put / 1e6:.1f} MB, the longest send backlog {last.seconds(last.peak_backlog_bytes):.1f} s"
    console.print(f"agent {agent_id}: finished; the coordinator has every message{peak}")


@interrupt_leaves_nothing
@user_errors
@with_prior
def robot(
    path: InputArgument,
    out: OutOption,
    robot_id: int = typer.Option(..., "--id", min=0, help="This robot's id (0 to N-1)."),
    robots: int = typer.Option(
        ...,
        "--robots",
        min=1,
        help="Robots in the team, ids 0 to N-1 (each runs como3r robot with its --id).",
    ),
    listen: ListenOption = [],
    connect: ConnectOption = [],
    schedule: Path | None = typer.Option(
        None,
        "--schedule",
        metavar="FILE",
        help="Rendezvous schedule, the same file on every robot: lines "
        "robot_id\\[@point],start_s,end_s (more start_s,end_s pairs may follow) of "
        "mission time in range of a rendezvous point (robots at one point at one time "
        "meet); a robot without a line is never in range (default: the configuration's "
        "decentralized.protocol.schedule; none: always in range).",
    ),
    prior_spec: Any = None,
    config_file: ConfigOption = None,
    overrides: SetOption = [],
    calib: CalibOption = False,
    session: SessionOption = "como3r",
    scouting: ScoutingOption = False,
    zenoh_config: ZenohConfigOption = None,
    team: TeamOption = None,
    max_mbps: MaxMbpsOption = 0.0,
    overwrite: OverwriteOption = False,
    quiet: QuietOption = False,
) -> None:
    """One robot of the decentralized mode (FLOCC-SLAM), talking to its peers over Zenoh.

    Waits until the whole team has started, runs the rendezvous rounds of the schedule
    (messages from robots out of range are dropped here, at the receiver) and writes this
    robot's output folder."""
    from como3r.decentralized.robot_node import run_robot
    from como3r.decentralized.schedule import read_schedule

    if robots > 1 and not (listen or connect or scouting):
        raise InputError(
            "give --listen and/or --connect endpoints (or --scouting) so the "
            "robots can find each other"
        )
    if not path.exists():
        raise InputError(f"{path}: robot input does not exist")
    network = _network(
        listen, connect, scouting, zenoh_config, session, team, "robot", robot_id, robots
    )
    network = dataclasses.replace(network, max_mbps=max_mbps)
    config = config_from_options(config_file, overrides, calib, False)
    plan = read_schedule(schedule) if schedule is not None else None
    if robots > 1 and not quiet:  # it waits for the whole team: say where it looks
        err_console.print(
            f"robot {robot_id}: waiting for the team of {robots} robot(s) ({network.where()})",
            markup=False,
            highlight=False,
            soft_wrap=True,
        )
    with run_progress(quiet) as shown:
        summary = run_robot(
            network,
            robot_id,
            robots,
            path,
            out,
            config,
            prior_spec,
            plan,
            overwrite=overwrite,
            progress=shown,
        )
    print_summary(summary, out)
