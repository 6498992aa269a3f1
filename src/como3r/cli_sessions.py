"""``como3r merge``: two finished runs' maps into one (:mod:`como3r.runtime.merge`;
manual: docs/sessions.md, "Maps of several days").
"""

from __future__ import annotations

from pathlib import Path

import typer

from como3r.cli_checks import print_summary
from como3r.cli_common import interrupt_leaves_nothing, user_errors
from como3r.cli_network import (
    CodebookOption,
    DeviceOption,
    OutOption,
    OverwriteOption,
    PrecisionOption,
    PriorOption,
    QuietOption,
    RetrievalOption,
    WeightsOption,
    _prior_spec,
)
from como3r.cli_progress import run_progress


@interrupt_leaves_nothing
@user_errors
def merge(
    first: Path = typer.Argument(
        ...,
        metavar="A",
        show_default=False,
        help="A finished run's folder: its agents keep their ids and its frame is kept.",
    ),
    second: Path = typer.Argument(
        ...,
        metavar="B",
        show_default=False,
        help="Another finished run's folder, made with the same "
        "configuration: its agents follow A's.",
    ),
    out: OutOption = ...,
    prior: PriorOption = "mast3r",
    weights: WeightsOption = None,
    retrieval_weights: RetrievalOption = None,
    codebook: CodebookOption = None,
    device: DeviceOption = "cpu",
    precision: PrecisionOption = "auto",
    overwrite: OverwriteOption = False,
    quiet: QuietOption = False,
) -> None:
    """Merge the maps of two finished runs where they see the same places.

    B's keyframes meet A's map as a new agent's would; if none is recognized, nothing is
    written."""
    from como3r.io.output import check_output_dir
    from como3r.runtime.merge import merge_runs

    spec = _prior_spec(prior, weights, retrieval_weights, codebook, device, precision)
    check_output_dir(out, overwrite)
    with run_progress(quiet) as shown:
        summary = merge_runs(first, second, out, spec, overwrite=overwrite, progress=shown)
    print_summary(summary, out)
