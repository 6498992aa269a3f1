"""Choice of the MASt3R compute precision (``--precision auto|fp32|bf16|fp16``).

bfloat16 pays off only where the hardware multiplies it natively: CUDA GPUs of compute
capability >= 8.0 (Ampere and later), and CPUs with AMX or AVX512-BF16. On a CPU without
them bf16 matmuls are emulated and run several times slower than float32, so ``auto`` picks
float32 there. float16 is refused on CPU (no speed-up measured; its range can overflow the
encoder's residual stream).
"""

from __future__ import annotations

import logging
from pathlib import Path

import torch

from como3r.errors import ConfigError

logger = logging.getLogger(__name__)

PRECISIONS = ("auto", "fp32", "bf16", "fp16")
_DTYPES = {"fp32": torch.float32, "bf16": torch.bfloat16, "fp16": torch.float16}
#: /proc/cpuinfo flags of native bf16 matrix instructions (Intel AMX, AVX512-BF16)
CPU_BF16_FLAGS = frozenset({"amx_bf16", "avx512_bf16"})
CPUINFO = Path("/proc/cpuinfo")


def cpu_flags(cpuinfo: Path | None = None) -> frozenset[str]:
    """The CPU feature flags listed in ``cpuinfo`` (default :data:`CPUINFO`); empty where it
    is unreadable (not Linux)."""
    try:
        text = (cpuinfo or CPUINFO).read_text(errors="replace")
    except OSError:
        return frozenset()
    for line in text.splitlines():
        name, _, value = line.partition(":")
        if name.strip() == "flags":
            return frozenset(value.split())
    return frozenset()


def cpu_supports_bf16() -> bool:
    """True when this CPU has AMX-BF16 or AVX512-BF16 instructions.

    torch 2.13 exposes only the vector ISA level (``torch.backends.cpu.get_cpu_capability()``
    says ``"AVX512"`` with or without BF16), so the flags come from ``/proc/cpuinfo``; other
    systems report False (float32 is the safe choice).
    """
    return bool(cpu_flags() & CPU_BF16_FLAGS)


def cuda_supports_bf16(device: torch.device) -> bool:
    """True for a CUDA device of compute capability >= 8.0."""
    return torch.cuda.get_device_capability(device) >= (8, 0)


def check_precision(device: torch.device | str, precision: str) -> None:
    """Raise :class:`ConfigError` for an unknown ``precision`` or fp16 on a CPU ``device``."""
    if precision not in PRECISIONS:
        raise ConfigError(f"unknown precision {precision!r}; choose one of {', '.join(PRECISIONS)}")
    if precision == "fp16" and torch.device(device).type == "cpu":
        raise ConfigError("precision fp16 is not supported on CPU; use auto, fp32 or bf16")


def choose_dtype(device: torch.device, precision: str) -> torch.dtype:
    """The compute dtype of MASt3R's encoder and decoders for ``precision`` on ``device``.

    Args:
        device: ``cpu`` or ``cuda[:k]`` (already checked to exist).
        precision: ``"auto"`` (bf16 where the hardware supports it natively, else fp32),
            ``"fp32"``, ``"bf16"`` or ``"fp16"``.

    Raises:
        ConfigError: unknown precision, or fp16 on CPU.
    """
    check_precision(device, precision)
    if precision != "auto":
        return _DTYPES[precision]
    if device.type == "cuda":
        native = cuda_supports_bf16(device)
        hardware = "CUDA compute capability >= 8.0" if native else "CUDA compute capability < 8.0"
    else:
        native = cpu_supports_bf16()
        hardware = "CPU with AMX/AVX512-BF16" if native else "CPU without AMX/AVX512-BF16"
    dtype = torch.bfloat16 if native else torch.float32
    logger.info("MASt3R precision auto -> %s (%s)", "bf16" if native else "fp32", hardware)
    return dtype
