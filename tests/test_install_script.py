"""scripts/install.sh chooses the torch build: each branch, run against a fake ``python``.

The fake logs every call and answers ``import torch`` as told; PATH holds only it (and,
for the driver branch, a fake ``nvidia-smi``), so the machine's own torch and driver do
not leak in.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "install.sh"
CPU_INDEX = "https://download.pytorch.org/whl/cpu"

FAKE_PYTHON = """#!{bash}
call="$*"
echo "${{call//$'\\n'/ }}" >> "{log}"
if [ "$1" = "-c" ]; then
    case "$2" in
        *print*) echo 9.9.9; exit 0 ;;
        *urlopen*) [ "{cpu_index_up}" = "1" ]; exit $? ;;
        *) [ "{torch_installed}" = "1" ]; exit $? ;;
    esac
fi
case "$*" in
    *"--index-url {cpu_index}"*) [ "{cpu_index_pip_ok}" = "1" ]; exit $? ;;
esac
exit 0
"""


def _run(
    tmp_path: Path,
    *,
    torch_installed: bool = False,
    cpu_index_up: bool = True,
    cpu_index_pip_ok: bool = True,
    driver: bool = False,
    dry_run: bool = True,
    env: dict[str, str] | None = None,
    args: tuple[str, ...] = (),
) -> tuple[subprocess.CompletedProcess[str], list[str]]:
    """Run install.sh with a fake python on a PATH of nothing else; (result, python calls)."""
    bash = shutil.which("bash")
    assert bash is not None
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    log = tmp_path / "calls.log"
    log.touch()
    fake = bin_dir / "python"
    fake.write_text(
        FAKE_PYTHON.format(
            bash=bash,
            log=log,
            torch_installed=int(torch_installed),
            cpu_index=CPU_INDEX,
            cpu_index_up=int(cpu_index_up),
            cpu_index_pip_ok=int(cpu_index_pip_ok),
        )
    )
    fake.chmod(0o755)
    dirname = shutil.which("dirname")
    assert dirname is not None
    (bin_dir / "dirname").symlink_to(dirname)
    if driver:
        smi = bin_dir / "nvidia-smi"
        smi.write_text(f"#!{bash}\necho 'GPU 0: fake'\n")
        smi.chmod(0o755)
    full_env = {
        "PATH": str(bin_dir),
        "HOME": str(tmp_path),
        "COMO3R_INSTALL_DRY_RUN": "1" if dry_run else "0",
        **(env or {}),
    }
    result = subprocess.run(
        [bash, str(SCRIPT), *args], env=full_env, capture_output=True, text=True, check=False
    )
    return result, log.read_text().splitlines()


def _pip_calls(calls: list[str]) -> list[str]:
    return [c for c in calls if c.startswith("-m pip")]


def test_installed_torch_is_kept(tmp_path: Path) -> None:
    result, calls = _run(tmp_path, torch_installed=True)
    assert result.returncode == 0, result.stderr
    assert "keeping the installed torch 9.9.9" in result.stdout
    would_run = [line for line in result.stdout.splitlines() if "would run" in line]
    assert would_run == ["como3r: would run: python -m pip install -e ."]


def test_como3r_torch_chooses_the_requirement(tmp_path: Path) -> None:
    result, _ = _run(tmp_path, env={"COMO3R_TORCH": "torch==2.5.1"})
    assert result.returncode == 0, result.stderr
    assert "would run: python -m pip install torch==2.5.1\n" in result.stdout
    assert CPU_INDEX not in result.stdout


def test_no_driver_takes_the_cpu_index(tmp_path: Path) -> None:
    result, _ = _run(tmp_path)
    assert result.returncode == 0, result.stderr
    assert (
        f"would run: python -m pip install --index-url {CPU_INDEX} --timeout 10 "
        "--retries 0 torch==2.13.0"
    ) in result.stdout


def test_driver_takes_pypi_default_build(tmp_path: Path) -> None:
    result, _ = _run(tmp_path, driver=True)
    assert result.returncode == 0, result.stderr
    assert "would run: python -m pip install torch>=2.4\n" in result.stdout
    assert CPU_INDEX not in result.stdout


def test_como3r_torch_index_replaces_the_cpu_index(tmp_path: Path) -> None:
    mirror = "https://mirror.example/whl/cpu"
    result, _ = _run(tmp_path, env={"COMO3R_TORCH_INDEX": mirror})
    assert result.returncode == 0, result.stderr
    assert f"would run: python -m pip install --index-url {mirror} torch==2.13.0" in result.stdout
    assert CPU_INDEX not in result.stdout


@pytest.mark.parametrize("case", ["up", "unreachable", "pip_fails"])
def test_unreachable_cpu_index_falls_back_to_pypi_and_says_so(tmp_path: Path, case: str) -> None:
    """The index is probed first (pip with find-links or an extra index in the user's pip
    configuration skips an unreachable --index-url silently, so only the probe can say it);
    a pip install from a reachable index that still fails falls back the same way."""
    result, calls = _run(
        tmp_path,
        cpu_index_up=case != "unreachable",
        cpu_index_pip_ok=case != "pip_fails",
        dry_run=False,
    )
    assert result.returncode == 0, result.stderr
    probes = [c for c in calls if c.startswith("-c") and "urlopen" in c]
    assert len(probes) == 1 and probes[0].endswith(f"{CPU_INDEX}/torch/")
    pip = _pip_calls(calls)
    from_index = f"-m pip install --index-url {CPU_INDEX} --timeout 10 --retries 0 torch==2.13.0"
    notes = [line for line in result.stderr.splitlines() if "could not be reached" in line]
    if case == "up":
        assert pip == [from_index, "-m pip install -e ."]
        assert notes == []
    else:
        fallback = ["-m pip install torch==2.13.0", "-m pip install -e ."]
        assert pip == ([from_index] if case == "pip_fails" else []) + fallback
        assert len(notes) == 1 and "falling back to PyPI's torch==2.13.0" in notes[0]


def test_probe_answers_within_ten_seconds_for_an_unresolvable_index(tmp_path: Path) -> None:
    """The real probe (this interpreter, not the fake) on an index that does not resolve
    fails fast and the script falls back with its one line."""
    import os
    import sys
    import time

    bash = shutil.which("bash")
    assert bash is not None
    script = SCRIPT.read_text()
    probe = script[
        script.index("index_reachable() {") : script.index(
            "\n}\n", script.index("index_reachable() {")
        )
        + 3
    ]
    start = time.monotonic()
    result = subprocess.run(
        [bash, "-c", f"PY={sys.executable}\n{probe}\nindex_reachable http://nonexistent.invalid"],
        capture_output=True,
        text=True,
        check=False,
        timeout=30,
        env={"PATH": os.environ.get("PATH", ""), "HOME": str(tmp_path)},
    )  # no proxy variables
    assert result.returncode == 1
    assert time.monotonic() - start < 12


def test_test_extras(tmp_path: Path) -> None:
    result, _ = _run(tmp_path, torch_installed=True, args=("test",))
    assert result.returncode == 0, result.stderr
    assert "would run: python -m pip install -e .[test,viewer]" in result.stdout
