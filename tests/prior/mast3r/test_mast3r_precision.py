"""Choice of the MASt3R compute precision (``--precision``) with monkeypatched hardware probes."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from como3r.cli import app
from como3r.errors import ConfigError
from como3r.prior.mast3r import load_mast3r
from como3r.prior.mast3r import precision as precision_module
from como3r.prior.mast3r.precision import choose_dtype, cpu_flags, cpu_supports_bf16

CPU = torch.device("cpu")
CUDA = torch.device("cuda:0")


def _cpuinfo(tmp_path: Path, flags: str) -> Path:
    path = tmp_path / "cpuinfo"
    path.write_text(
        f"processor\t: 0\nmodel name\t: test\nflags\t\t: {flags}\n\n"
        f"processor\t: 1\nflags\t\t: {flags}\n"
    )
    return path


@pytest.mark.parametrize(
    ("flags", "expected"),
    [
        ("fpu sse avx2 avx512f avx512_bf16", True),
        ("fpu sse avx2 avx512f amx_tile amx_bf16", True),
        ("fpu sse avx2 avx512f avx512_vnni", False),
    ],
)
def test_cpu_supports_bf16_reads_cpuinfo_flags(tmp_path, monkeypatch, flags, expected):
    monkeypatch.setattr(precision_module, "CPUINFO", _cpuinfo(tmp_path, flags))
    assert cpu_flags() == frozenset(flags.split())
    assert cpu_supports_bf16() is expected


def test_unreadable_cpuinfo_means_no_flags(tmp_path):
    assert cpu_flags(tmp_path / "missing") == frozenset()


@pytest.mark.parametrize(("native", "expected"), [(True, torch.bfloat16), (False, torch.float32)])
def test_auto_on_cpu_follows_bf16_support(monkeypatch, native, expected):
    monkeypatch.setattr(precision_module, "cpu_supports_bf16", lambda: native)
    assert choose_dtype(CPU, "auto") == expected


@pytest.mark.parametrize(
    ("capability", "expected"),
    [((8, 0), torch.bfloat16), ((9, 0), torch.bfloat16), ((7, 5), torch.float32)],
)
def test_auto_on_cuda_follows_compute_capability(monkeypatch, capability, expected):
    monkeypatch.setattr(torch.cuda, "get_device_capability", lambda device=None: capability)
    assert choose_dtype(CUDA, "auto") == expected


@pytest.mark.parametrize(("name", "expected"), [("fp32", torch.float32), ("bf16", torch.bfloat16)])
def test_explicit_precision_ignores_hardware(monkeypatch, name, expected):
    monkeypatch.setattr(precision_module, "cpu_supports_bf16", lambda: expected != torch.bfloat16)
    assert choose_dtype(CPU, name) == expected


def test_fp16_only_on_cuda():
    assert choose_dtype(CUDA, "fp16") == torch.float16
    with pytest.raises(ConfigError, match="fp16 is not supported on CPU"):
        choose_dtype(CPU, "fp16")


def test_unknown_precision_is_refused():
    with pytest.raises(ConfigError, match="unknown precision 'int8'"):
        choose_dtype(CPU, "int8")


@pytest.mark.parametrize(("native", "dtype"), [(True, "bfloat16"), (False, "float32")])
def test_load_mast3r_auto_records_the_choice(tiny_checkpoint, monkeypatch, native, dtype):
    monkeypatch.setattr(precision_module, "cpu_supports_bf16", lambda: native)
    prior = load_mast3r(tiny_checkpoint, dtype="auto")
    assert prior.network.compute_dtype == getattr(torch, dtype)
    description = prior.describe()
    assert (description["dtype"], description["precision"]) == (dtype, "auto")


def test_load_mast3r_refuses_fp16_on_cpu_before_reading(tmp_path):
    with pytest.raises(ConfigError, match="fp16"):
        load_mast3r(tmp_path / "absent.pth", dtype="fp16")


def test_cli_refuses_fp16_on_cpu_with_one_error_line(tmp_path):
    result = CliRunner().invoke(
        app,
        [
            "run",
            "--agent",
            str(tmp_path),
            "--out",
            str(tmp_path / "out"),
            "--prior",
            "mast3r",
            "--weights",
            str(tmp_path / "w.pth"),
            "--precision",
            "fp16",
        ],
    )
    assert result.exit_code == 2
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and "fp16" in lines[0]
