"""``como3r weights`` and the weights cache, against a local HTTP server on 127.0.0.1 that
serves small files with ``Range`` support (and can break a transfer half-way)."""

from __future__ import annotations

import hashlib
import random
import re
import threading
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
from typer.testing import CliRunner

from como3r.cli import app
from como3r.errors import CheckpointError, InputError
from como3r.prior import weights
from como3r.prior.weights import DownloadError, WeightFile, fetch_file, file_status
from como3r.runtime.pipeline import PriorSpec, resolve_weights

from ..data.test_agent import write_agent

# no test here reads a figure of its runs' report.html (tests/conftest.py)
pytestmark = pytest.mark.usefixtures("undrawn_report_figures")

SIZE = 300_000


@dataclass
class Served:
    """What the server holds and what it was asked."""

    files: dict[str, bytes] = field(default_factory=dict)
    #: filename -> bytes after which the next response breaks off (once)
    cut: dict[str, int] = field(default_factory=dict)
    #: (filename, Range header or None, bytes sent) per request
    log: list[tuple[str, str | None, int]] = field(default_factory=list)
    #: answer every request with the whole file (200), as servers without Range support do
    ignore_range: bool = False


def _handler(served: Served) -> type[BaseHTTPRequestHandler]:
    class Handler(BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 - http.server's name
            name = self.path.rsplit("/", 1)[-1]
            data = served.files.get(name)
            if data is None:
                self.send_error(404)
                return
            asked = None if served.ignore_range else self.headers.get("Range")
            start = int(re.match(r"bytes=(\d+)-", asked).group(1)) if asked else 0
            body = (
                data[start : start + served.cut.pop(name)] if name in served.cut else data[start:]
            )
            served.log.append((name, asked, len(body)))  # before replying: the client may be fast
            if start >= len(data):
                self.send_response(416)
                self.send_header("Content-Range", f"bytes */{len(data)}")
                self.send_header("Content-Length", "0")
                self.end_headers()
                return
            self.send_response(206 if asked else 200)
            if asked:
                self.send_header("Content-Range", f"bytes {start}-{len(data) - 1}/{len(data)}")
            self.send_header("Content-Length", str(len(data) - start))
            self.end_headers()
            self.wfile.write(body)
            self.close_connection = True

        def log_message(self, *args) -> None:  # keep test output clean
            pass

    return Handler


@pytest.fixture(autouse=True)
def small_chunks(monkeypatch) -> None:
    """Several chunks per test file, so progress and resumption happen mid-file."""
    monkeypatch.setattr(weights, "CHUNK", 50_000)


@pytest.fixture
def server():
    """``(base_url, Served)`` of a server thread on 127.0.0.1."""
    served = Served()
    httpd = ThreadingHTTPServer(("127.0.0.1", 0), _handler(served))
    thread = threading.Thread(
        target=httpd.serve_forever, kwargs={"poll_interval": 0.02}, daemon=True
    )
    thread.start()
    yield f"http://127.0.0.1:{httpd.server_address[1]}/MASt3R", served
    httpd.shutdown()
    httpd.server_close()


def _file(data: bytes, sha256: str | None = "official") -> WeightFile:
    digest = hashlib.sha256(data).hexdigest() if sha256 == "official" else sha256
    return WeightFile("checkpoint", "net.pth", digest, "--weights")


def _data(seed: int) -> bytes:
    return random.Random(seed).randbytes(SIZE)


def test_complete_download_is_verified_and_recorded(server, tmp_path) -> None:
    url, served = server
    served.files["net.pth"] = data = _data(1)
    seen = []
    status = fetch_file(
        _file(data), tmp_path, url, progress=lambda done, total: seen.append((done, total))
    )
    assert status.state == "verified" and status.size == SIZE
    assert (tmp_path / "net.pth").read_bytes() == data
    assert not (tmp_path / "net.pth.part").exists()
    assert (
        tmp_path / "net.pth.sha256"
    ).read_text() == f"{hashlib.sha256(data).hexdigest()}  net.pth\n"
    assert seen[-1] == (SIZE, SIZE) and len(seen) > 1
    # accepted files are not fetched again
    assert fetch_file(_file(data), tmp_path, url).state == "verified"
    assert len(served.log) == 1


def test_interrupted_transfer_resumes_where_it_broke(server, tmp_path) -> None:
    url, served = server
    served.files["net.pth"] = data = _data(2)
    served.cut["net.pth"] = broken_at = 120_000
    with pytest.raises(DownloadError, match="run again to resume"):
        fetch_file(_file(data), tmp_path, url)
    assert (tmp_path / "net.pth.part").stat().st_size == broken_at
    assert file_status(_file(data), tmp_path).state == "partial"
    status = fetch_file(_file(data), tmp_path, url)
    assert status.state == "verified"
    assert (tmp_path / "net.pth").read_bytes() == data
    # the second request asked for, and got, only the rest
    assert served.log[1] == ("net.pth", f"bytes={broken_at}-", SIZE - broken_at)


def test_complete_part_file_is_finished_without_new_data(server, tmp_path) -> None:
    """A ``.part`` that already holds the whole file (416 to its Range) is accepted."""
    url, served = server
    served.files["net.pth"] = data = _data(3)
    (tmp_path / "net.pth.part").write_bytes(data)
    assert fetch_file(_file(data), tmp_path, url).state == "verified"
    assert served.log == [("net.pth", f"bytes={SIZE}-", 0)]


def test_part_longer_than_the_file_is_deleted_then_fetched_anew(server, tmp_path) -> None:
    url, served = server
    served.files["net.pth"] = data = _data(7)
    (tmp_path / "net.pth.part").write_bytes(data + b"more than the server has")
    with pytest.raises(DownloadError, match="longer than the file"):
        fetch_file(_file(data), tmp_path, url)
    assert not (tmp_path / "net.pth.part").exists()
    assert fetch_file(_file(data), tmp_path, url).state == "verified"


def test_only_http_urls(tmp_path) -> None:
    with pytest.raises(InputError, match="COMO3R_WEIGHTS_URL"):
        fetch_file(_file(b""), tmp_path, "file:///etc")


def test_server_without_range_support_restarts_the_file(server, tmp_path) -> None:
    url, served = server
    served.files["net.pth"] = data = _data(6)
    served.ignore_range = True
    (tmp_path / "net.pth.part").write_bytes(b"stale bytes of another attempt")
    assert fetch_file(_file(data), tmp_path, url).state == "verified"
    assert (tmp_path / "net.pth").read_bytes() == data


def test_wrong_checksum_is_refused_and_not_kept(server, tmp_path) -> None:
    url, served = server
    served.files["net.pth"] = _data(4)
    with pytest.raises(CheckpointError, match="not the official"):
        fetch_file(_file(b"", sha256="0" * 64), tmp_path, url)
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_file_without_official_checksum_needs_trust(server, tmp_path) -> None:
    url, served = server
    served.files["net.pth"] = data = _data(5)
    with pytest.raises(CheckpointError, match="--trust-unverified"):
        fetch_file(_file(data, sha256=None), tmp_path, url)
    assert served.log == [] and not any(tmp_path.iterdir())
    status = fetch_file(_file(data, sha256=None), tmp_path, url, trust_unverified=True)
    assert status.state == "unverified"
    assert status.sha256 == hashlib.sha256(data).hexdigest()


def test_cache_location_follows_the_environment(monkeypatch, tmp_path) -> None:
    monkeypatch.setenv("COMO3R_HOME", str(tmp_path / "home"))
    assert weights.weights_home() == tmp_path / "home"
    monkeypatch.delenv("COMO3R_HOME")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    assert weights.weights_home() == tmp_path / "cache" / "como3r"
    monkeypatch.delenv("COMO3R_WEIGHTS_URL", raising=False)
    assert weights.base_url() == weights.OFFICIAL_URL


# --- the command line ------------------------------------------------------------------


@pytest.fixture
def official_names(server, monkeypatch, tmp_path) -> tuple[Path, Served]:
    """The server holds small files under the release's names; the cache is empty."""
    url, served = server
    for k, file in enumerate(weights.WEIGHT_FILES):
        served.files[file.filename] = _data(10 + k)[: 1000 * (k + 1)]
    home = tmp_path / "home"
    monkeypatch.setenv("COMO3R_HOME", str(home))
    monkeypatch.setenv("COMO3R_WEIGHTS_URL", url)
    return home, served


def _cli(*args: str):
    return CliRunner().invoke(app, list(args))


def _one_error_line(result, fragment: str) -> None:
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and fragment in lines[0], lines


def test_cli_fetch_refuses_unverifiable_files_before_downloading(official_names) -> None:
    home, served = official_names
    _one_error_line(_cli("weights", "fetch"), "--trust-unverified")
    assert served.log == [] and not home.exists()


def test_cli_fetch_and_list(official_names) -> None:
    home, served = official_names
    result = _cli("weights", "fetch", "--trust-unverified")
    assert result.exit_code == 0, result.output
    for file in weights.WEIGHT_FILES:
        digest = hashlib.sha256(served.files[file.filename]).hexdigest()
        assert f"{file.filename}: unverified, sha256 {digest}" in result.output
        assert (home / file.filename).read_bytes() == served.files[file.filename]
    listing = _cli("weights", "list", "--check")
    assert listing.exit_code == 0, listing.output
    assert listing.output.count("unverified") == 3
    assert "1.0 kB" in listing.output and "3.0 kB" in listing.output
    assert _cli("weights", "path").output.strip() == str(home)


def test_cli_list_of_an_empty_cache(official_names) -> None:
    result = _cli("weights", "list")
    assert result.exit_code == 0 and result.output.count("missing") == 3, result.output


@pytest.mark.parametrize("prior", [[], ["--prior", "mast3r"]], ids=["default", "mast3r"])
def test_run_with_an_empty_cache_names_weights_fetch(official_names, tmp_path, prior) -> None:
    """Images alone: the error names the fetch (and its --trust-unverified) only."""
    out = tmp_path / "out"
    images = write_agent(tmp_path / "images", n=2)
    result = _cli("run", "--agent", str(images), "--out", str(out), *prior)
    _one_error_line(result, "como3r weights fetch --trust-unverified")
    assert "--prior simulated" not in result.output
    assert not out.exists() and not out.with_name("out.partial").exists()


def test_missing_weights_name_the_simulated_prior_for_rgbd_inputs(official_names, tmp_path) -> None:
    """Every input has metric depth, intrinsics and ground-truth poses: the error says they
    also run with --prior simulated, and what that is."""
    rgbd = [
        write_agent(
            tmp_path / f"agent_{k}", n=2, depth="npy", calib="20 20 16 12", groundtruth=True
        )
        for k in range(2)
    ]
    result = _cli(
        "run", "--agent", str(rgbd[0]), "--agent", str(rgbd[1]), "--out", str(tmp_path / "out")
    )
    _one_error_line(result, "como3r weights fetch --trust-unverified")
    _one_error_line(result, "also run with --prior simulated")
    assert "does not measure MASt3R" in result.output
    mixed = _cli(
        "run",
        "--agent",
        str(rgbd[0]),
        "--agent",
        str(write_agent(tmp_path / "images", n=2)),
        "--out",
        str(tmp_path / "out"),
    )
    _one_error_line(mixed, "--trust-unverified")
    assert "--prior simulated" not in mixed.output


def test_run_takes_all_three_files_from_the_cache(official_names) -> None:
    home, _ = official_names
    assert _cli("weights", "fetch", "--trust-unverified").exit_code == 0
    spec = resolve_weights(PriorSpec("mast3r"))
    assert (spec.weights, spec.retrieval_weights, spec.codebook) == tuple(
        home / f.filename for f in weights.WEIGHT_FILES
    )
    # an explicit checkpoint does not take the cached retrieval head made for another
    assert resolve_weights(PriorSpec("mast3r", weights=Path("own.pth"))).retrieval_weights is None


def test_cli_fetch_progress_lines_and_quiet(official_names, tmp_path, monkeypatch) -> None:
    """Not on a terminal: one line per file as its download completes (as run's plain
    progress); --quiet: none, the cache and the files' statuses still printed."""
    plain = _cli("weights", "fetch", "--trust-unverified")
    assert plain.exit_code == 0, plain.output
    lines = [
        line.split("] ", 1)[1]
        for line in plain.output.splitlines()
        if re.match(r"^\[\d+:\d\d:\d\d\] ", line)
    ]
    assert lines == [
        f"{file.role}: {k + 1}.0 kB/{k + 1}.0 kB" for k, file in enumerate(weights.WEIGHT_FILES)
    ]
    monkeypatch.setenv("COMO3R_HOME", str(tmp_path / "other"))
    quiet = _cli("weights", "fetch", "--trust-unverified", "--quiet")
    assert quiet.exit_code == 0, quiet.output
    assert not re.search(r"^\[\d+:\d\d:\d\d\] ", quiet.output, re.M), quiet.output
    assert quiet.output.startswith(f"weights cache: {tmp_path / 'other'}")
    assert quiet.output.count(": unverified, sha256 ") == 3
