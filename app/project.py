"""The app's project folder: everything the analyst decided and everything computed, on disk.

Layout of a project folder::

    project.json     session: inputs, γ, calibration frame, seed, reference frame, preset,
                     view settings, result folder, marked points (written atomically)
    LINES.json       the analyst's polylines in registration.calibration's LINES.json format
    POINTS.csv       marked ground points in registration.evaluation's POINTS.csv format
    result/          registration result folder (registration.load), written frame by frame
    uploads/         files uploaded through the browser

Every write goes to a temporary file in the same folder and is moved into place with
``os.replace``, so a crash or a kill never leaves a half-written file.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any

PROJECT_FILE = "project.json"
FORMAT_VERSION = 1


def write_atomic(path: Path, data: bytes | str) -> None:
    """Write ``data`` to ``path`` through a temporary file and ``os.replace``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    raw = data.encode("utf-8") if isinstance(data, str) else data
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(raw)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def default_project_dir(frames: str | None, base: str | None, data_dir: Path | None = None) -> Path:
    """Per-input project folder under the user's data dir (``platformdirs.user_data_dir``).

    The folder name is a short hash of the resolved input paths, so reopening the same inputs
    reopens the same session.
    """
    if data_dir is None:
        import platformdirs

        data_dir = Path(platformdirs.user_data_dir("aerialreg"))
    key = "\n".join(
        str(Path(p).expanduser().resolve()) if p else "-" for p in (frames, base)
    ).encode()
    stem = Path(frames).stem if frames else "demo"
    stem = "".join(c if c.isalnum() or c in "-_" else "_" for c in stem)[:40] or "input"
    return data_dir / "projects" / f"{stem}-{hashlib.sha1(key).hexdigest()[:10]}"


class Project:
    """A project folder; :meth:`load` / :meth:`save` the session dictionary."""

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder).expanduser().resolve()
        self.folder.mkdir(parents=True, exist_ok=True)

    @property
    def session_path(self) -> Path:
        return self.folder / PROJECT_FILE

    @property
    def lines_path(self) -> Path:
        return self.folder / "LINES.json"

    @property
    def points_path(self) -> Path:
        return self.folder / "POINTS.csv"

    @property
    def result_dir(self) -> Path:
        return self.folder / "result"

    @property
    def uploads_dir(self) -> Path:
        return self.folder / "uploads"

    def load(self) -> dict[str, Any]:
        """The saved session, or ``{}`` for a new project.

        Raises:
            ValueError: naming the file when project.json exists but is not a JSON object.
        """
        if not self.session_path.exists():
            return {}
        try:
            data = json.loads(self.session_path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as exc:
            raise ValueError(f"unreadable project file {self.session_path}: {exc}") from None
        if not isinstance(data, dict):
            raise ValueError(f"project file {self.session_path} does not hold a JSON object")
        return data

    def save(self, session: dict[str, Any]) -> None:
        data = dict(session)
        data["version"] = FORMAT_VERSION
        write_atomic(self.session_path, json.dumps(data, indent=1, sort_keys=True))

    def archive_result(self) -> Path:
        """Move the result folder aside (``result.prev-N``) so a fresh run can start; returns it."""
        n = 1
        while (self.folder / f"result.prev-{n}").exists():
            n += 1
        target = self.folder / f"result.prev-{n}"
        os.replace(self.result_dir, target)
        return target

    def write_file(self, name: str, data: bytes | str) -> Path:
        path = self.folder / name
        write_atomic(path, data)
        return path


def resolve_allowed(path_text: str, allowed: list[Path]) -> Path:
    """Resolve a user-typed path (symlinks too) and check it lies inside an allowed folder.

    Glob patterns are checked through their fixed leading part (the folder before the first
    wildcard).

    Raises:
        ValueError: naming the path when it is empty or outside every allowed folder.
        FileNotFoundError: naming the path when nothing exists there (globs: the folder).
    """
    text = path_text.strip()
    if not text:
        raise ValueError("empty path")
    p = Path(text).expanduser()
    is_glob = any(ch in text for ch in "*?[")
    if is_glob:
        parts = p.parts
        fixed = []
        for part in parts:
            if any(ch in part for ch in "*?["):
                break
            fixed.append(part)
        anchor = Path(*fixed) if fixed else Path(".")
        resolved_anchor = anchor.resolve()
        check = resolved_anchor
        result = resolved_anchor.joinpath(*parts[len(fixed) :])
    else:
        check = result = p.resolve()
    roots = [Path(a).expanduser().resolve() for a in allowed]
    if not any(check == r or r in check.parents for r in roots):
        raise ValueError(
            f"path {text!r} is outside the allowed folders ({', '.join(str(r) for r in roots)})"
        )
    if not check.exists():
        raise FileNotFoundError(f"no such file or folder: {text!r}")
    return result
