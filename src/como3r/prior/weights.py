"""The MASt3R weight files: where they come from, where they are kept, how they are fetched.

Three files make up the official release (naver/mast3r README, "Checkpoints"), all served
from ``https://download.europe.naverlabs.com/ComputerVision/MASt3R/<file>``:

* the network, ``MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.pth`` (about 2.75 GB);
* the retrieval head, ``..._retrieval_trainingfree.pth`` (about 8.4 MB);
* the ASMK codebook, ``..._retrieval_codebook.pkl`` (about 268 MB).

They are kept in the weights cache, ``$COMO3R_HOME`` (default ``$XDG_CACHE_HOME/como3r``,
else ``~/.cache/como3r``). ``COMO3R_WEIGHTS_URL`` replaces the base URL (a mirror, or a
local server in the tests).

A download goes to ``<file>.part`` and resumes from its end with an HTTP ``Range`` request;
its SHA-256 is computed on the way. A file becomes ``<file>`` (with ``<file>.sha256`` in
``sha256sum`` format beside it) only once accepted: its SHA-256 equals the value recorded
here, or no value is recorded and the caller passed ``trust_unverified``. A file whose
SHA-256 differs from the recorded one is deleted.
"""

from __future__ import annotations

import hashlib
import http.client
import os
import re
import urllib.error
import urllib.request
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from como3r.errors import CheckpointError, Como3rError, InputError

HOME_VARIABLE = "COMO3R_HOME"
URL_VARIABLE = "COMO3R_WEIGHTS_URL"
OFFICIAL_URL = "https://download.europe.naverlabs.com/ComputerVision/MASt3R"
#: bytes read per network or disk read
CHUNK = 1 << 20
#: seconds without data before a download gives up (it resumes when run again)
TIMEOUT_S = 60.0

#: ``(done_bytes, total_bytes or None)`` after every chunk of a download
Progress = Callable[[int, "int | None"], None]


class DownloadError(Como3rError):
    """A download that could not be completed (network, server); running again resumes it."""


@dataclass(frozen=True)
class WeightFile:
    """One file of the release.

    Attributes:
        role: ``checkpoint``, ``retrieval`` or ``codebook``.
        filename: its name on the server and in the cache.
        sha256: the official SHA-256 in hex, or None where none is published.
        option: the ``como3r run`` option that gives it explicitly.
    """

    role: str
    filename: str
    sha256: str | None
    option: str


# No SHA-256 of these files is published: not in the naver/mast3r README or its issues, nor
# beside the files on download.europe.naverlabs.com; the Hugging Face repositories
# naver/MASt3R_* hold model.safetensors, different bytes from these .pth files. Searched
# 2026-11 (GitHub code and issues, web pages). Until one is published, `como3r weights fetch`
# accepts them only with --trust-unverified and prints the SHA-256 it computed.
WEIGHT_FILES: tuple[WeightFile, ...] = (
    WeightFile(
        "checkpoint", "MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.pth", None, "--weights"
    ),
    WeightFile(
        "retrieval",
        "MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric_retrieval_trainingfree.pth",
        None,
        "--retrieval-weights",
    ),
    WeightFile(
        "codebook",
        "MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric_retrieval_codebook.pkl",
        None,
        "--codebook",
    ),
)


def weights_home() -> Path:
    """The weights cache: ``$COMO3R_HOME``, else ``$XDG_CACHE_HOME/como3r``, else
    ``~/.cache/como3r``."""
    home = os.environ.get(HOME_VARIABLE)
    if home:
        return Path(home).expanduser()
    cache = os.environ.get("XDG_CACHE_HOME")
    return (Path(cache) if cache else Path.home() / ".cache") / "como3r"


def base_url() -> str:
    """Where the files are fetched from: ``$COMO3R_WEIGHTS_URL`` or the official server."""
    return os.environ.get(URL_VARIABLE) or OFFICIAL_URL


def weight_file(role: str) -> WeightFile:
    """The release file with this role."""
    return next(f for f in WEIGHT_FILES if f.role == role)


def cached_file(role: str, home: Path | None = None) -> Path:
    """The accepted file with this role in the cache.

    Raises:
        InputError: not there (one line naming ``como3r weights fetch``, with
            ``--trust-unverified`` while no official SHA-256 of the release is published, the
            option that names the file; ``como3r run`` adds ``--prior simulated`` where every
            input could run with it).
    """
    file = weight_file(role)
    path = (home or weights_home()) / file.filename
    if not path.is_file():
        fetch = (
            "`como3r weights fetch`"
            if all(f.sha256 for f in WEIGHT_FILES)
            else "`como3r weights fetch --trust-unverified` (no official SHA-256 is published "
            "for the release)"
        )
        raise InputError(
            f"--prior mast3r: no {file.filename} in {path.parent}; run {fetch} "
            f"or pass {file.option} FILE"
        )
    return path


# ---------------------------------------------------------------------------------------
# Status of the cache
# ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FileStatus:
    """What the cache holds for one release file.

    Attributes:
        file: the release file.
        path: where it is (or would be) kept.
        size: bytes on disk (of the ``.part`` file when only that exists), 0 when absent.
        state: ``verified`` (SHA-256 equals the official one), ``unverified`` (accepted
            without an official value), ``mismatch``, ``not checked`` (no ``.sha256`` beside
            it: not fetched by como3r), ``partial`` or ``missing``.
        sha256: its SHA-256 as recorded at fetch (or recomputed), if known.
    """

    file: WeightFile
    path: Path
    size: int
    state: str
    sha256: str | None


def file_status(file: WeightFile, home: Path | None = None, rehash: bool = False) -> FileStatus:
    """The state of one release file in the cache; ``rehash`` recomputes its SHA-256
    instead of trusting the ``.sha256`` written when it was fetched."""
    path = (home or weights_home()) / file.filename
    part = _part(path)
    if not path.is_file():
        if part.is_file():
            return FileStatus(file, path, part.stat().st_size, "partial", None)
        return FileStatus(file, path, 0, "missing", None)
    digest = sha256_of(path) if rehash else _recorded_digest(path)
    if digest is None:
        state = "not checked"
    elif file.sha256 is None:
        state = "unverified"
    else:
        state = "verified" if digest == file.sha256 else "mismatch"
    return FileStatus(file, path, path.stat().st_size, state, digest)


def sha256_of(path: Path) -> str:
    """SHA-256 of a file in hex, read in chunks."""
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        for chunk in iter(lambda: handle.read(CHUNK), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _part(path: Path) -> Path:
    return path.with_name(path.name + ".part")


def _digest_file(path: Path) -> Path:
    return path.with_name(path.name + ".sha256")


def _recorded_digest(path: Path) -> str | None:
    """The hex digest in ``<path>.sha256`` (``sha256sum`` format), if that file exists."""
    try:
        text = _digest_file(path).read_text()
    except OSError:
        return None
    match = re.match(r"([0-9a-f]{64})\s", text)
    return match.group(1) if match else None


# ---------------------------------------------------------------------------------------
# Fetching
# ---------------------------------------------------------------------------------------


def check_trust(files: Sequence[WeightFile], trust_unverified: bool) -> None:
    """Refuse, before any download, files without an official SHA-256 unless trusted.

    Raises:
        CheckpointError: one such file and no ``trust_unverified``.
    """
    unknown = [f.role for f in files if f.sha256 is None]
    if unknown and not trust_unverified:
        raise CheckpointError(
            f"no official SHA-256 is published for {', '.join(unknown)}: como3r cannot "
            "verify them; `como3r weights fetch --trust-unverified` downloads them all the "
            "same and prints the SHA-256 it computed"
        )


def fetch_file(
    file: WeightFile,
    home: Path | None = None,
    url: str | None = None,
    trust_unverified: bool = False,
    progress: Progress | None = None,
) -> FileStatus:
    """Download one release file into the cache (resuming a ``.part``) and accept it.

    Args:
        file: the release file.
        home: the cache folder (default :func:`weights_home`).
        url: base URL; the file is at ``<url>/<filename>`` (default :func:`base_url`).
        trust_unverified: accept a file that has no official SHA-256.
        progress: called with ``(done_bytes, total_bytes)`` as data arrives.

    Returns:
        The file's status: ``verified`` or ``unverified``, with its SHA-256. A file already
        accepted in the cache is not downloaded again.

    Raises:
        CheckpointError: no official SHA-256 and not ``trust_unverified``, or a SHA-256
            different from the official one (the download is deleted).
        DownloadError: the transfer failed; the ``.part`` stays and the next call resumes.
    """
    check_trust([file], trust_unverified)
    url = url or base_url()
    if not url.startswith(("https://", "http://")):
        raise InputError(f"{URL_VARIABLE}: {url!r} is not an http(s) URL")
    home = home or weights_home()
    status = file_status(file, home)
    if status.state in ("verified", "unverified"):
        return status
    path = home / file.filename
    if status.state == "not checked":  # placed there by hand: check it instead of fetching
        _accept(file, path, sha256_of(path), "the file in the cache")
        return file_status(file, home)
    home.mkdir(parents=True, exist_ok=True)
    digest = _download(f"{url.rstrip('/')}/{file.filename}", _part(path), progress)
    _accept(file, _part(path), digest, "the download")
    _part(path).replace(path)
    return file_status(file, home)


def _accept(file: WeightFile, path: Path, digest: str, what: str) -> None:
    """Record ``digest`` beside the cached file, or delete ``path`` if it is not official.

    Raises:
        CheckpointError: ``digest`` differs from the official SHA-256.
    """
    if file.sha256 is not None and digest != file.sha256:
        path.unlink()
        raise CheckpointError(
            f"{file.filename}: SHA-256 {digest} is not the official "
            f"{file.sha256}; {what} was deleted"
        )
    _digest_file(path.with_name(file.filename)).write_text(f"{digest}  {file.filename}\n")


def _download(url: str, part: Path, progress: Progress | None) -> str:
    """Append the rest of ``url`` to ``part`` (``Range`` from its size); returns the
    SHA-256 of the whole file.

    A server that ignores ``Range`` (200) restarts the file; 416 with ``part`` as long as
    the file means ``part`` is already complete.
    """
    digest, done = hashlib.sha256(), 0
    if part.is_file():
        with part.open("rb") as handle:
            for chunk in iter(lambda: handle.read(CHUNK), b""):
                digest.update(chunk)
                done += len(chunk)
    request = urllib.request.Request(url, headers={"Range": f"bytes={done}-"} if done else {})
    try:
        response = urllib.request.urlopen(request, timeout=TIMEOUT_S)  # noqa: S310 - checked
    except urllib.error.HTTPError as exc:
        if exc.code == 416 and _total_of(exc.headers.get("Content-Range")) == done:
            if progress is not None:
                progress(done, done)
            return digest.hexdigest()
        if exc.code == 416:  # longer than the server's file: not a prefix of it
            part.unlink()
            raise DownloadError(
                f"{url}: the partial download was longer than the file on "
                "the server and was deleted; run again"
            ) from None
        raise DownloadError(f"{url}: HTTP {exc.code} {exc.reason}") from None
    except (urllib.error.URLError, OSError) as exc:
        reason = getattr(exc, "reason", exc)
        raise DownloadError(f"{url}: {reason}; run again to resume") from None
    with response:
        if response.status != 206 and done:  # the server sent the whole file again
            digest, done = hashlib.sha256(), 0
        total = _total_of(response.headers.get("Content-Range"))
        if total is None and response.headers.get("Content-Length") is not None:
            total = done + int(response.headers["Content-Length"])
        _append(response, part, digest, done, total, progress, url)
    return digest.hexdigest()


def _append(
    response, part: Path, digest, done: int, total: int | None, progress: Progress | None, url: str
) -> None:
    """Stream ``response`` onto the end of ``part`` (a new file when ``done`` is 0),
    updating ``digest``.

    Raises:
        DownloadError: the connection broke or ended before ``total`` bytes.
    """
    mode = "ab" if done else "wb"
    with part.open(mode) as handle:
        try:
            for chunk in iter(lambda: response.read(CHUNK), b""):
                handle.write(chunk)
                digest.update(chunk)
                done += len(chunk)
                if progress is not None:
                    progress(done, total)
        except (OSError, http.client.HTTPException) as exc:
            raise DownloadError(
                f"{url}: transfer broke after {done} bytes ({exc}); run again to resume"
            ) from None
    if total is not None and done != total:
        raise DownloadError(
            f"{url}: the connection closed after {done} of {total} bytes; run again to resume"
        )


def _total_of(content_range: str | None) -> int | None:
    """The full length in a ``Content-Range`` header (``bytes a-b/N`` or ``bytes */N``)."""
    match = re.search(r"/(\d+)\s*$", content_range or "")
    return int(match.group(1)) if match else None
