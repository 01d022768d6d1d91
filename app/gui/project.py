"""The app's project folder: everything the analyst decided and everything computed, on disk.

Layout of a project folder::

    project.json     session: inputs, γ, calibration frame, seed, reference frame, preset,
                     view settings, result folder, marked points (written atomically)
    LINES.json       the analyst's polylines in registration.lens.gamma_from_lines's LINES.json format
    POINTS.csv       marked ground points in registration.evaluation's POINTS.csv format
    result/          registration result folder (registration.load), written frame by frame
    uploads/         files uploaded through the browser

Every write goes through the library's atomic writer (:func:`registration.io.atomic_path`), so
a crash or a kill never leaves a half-written file.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path
from typing import Any

from registration.io import write_bytes_atomic

PROJECT_FILE = "project.json"
FORMAT_VERSION = 1


def write_atomic(path: Path, data: bytes | str) -> None:
    """Write ``data`` (text as UTF-8) to ``path`` atomically (:func:`registration.io.atomic_path`)."""
    write_bytes_atomic(path, data.encode("utf-8") if isinstance(data, str) else data)


UPLOADS = "uploads"


def input_identity(path: str | None) -> str:
    """What identifies an input for choosing its project: its resolved path, or for a file
    uploaded into a project (``<project>/uploads/<kind>-<content hash>-<name>``) its file name,
    which carries the content's hash and survives the file moving between projects."""
    if not path:
        return "-"
    p = Path(path).expanduser()
    if p.parent.name == UPLOADS and (p.parent.parent / PROJECT_FILE).exists():
        return f"upload:{p.name}"
    return str(p.resolve())


def default_project_dir(frames: str | None, base: str | None, data_dir: Path | None = None) -> Path:
    """Per-input project folder under the user's data dir (``platformdirs.user_data_dir``).

    The folder name is a short hash of the inputs' identities (:func:`input_identity`), so
    reopening the same inputs (or uploading the same files again) reopens the same session.
    """
    if data_dir is None:
        import platformdirs

        data_dir = Path(platformdirs.user_data_dir("aerialreg"))
    key = "\n".join(input_identity(p) for p in (frames, base)).encode()
    stem = Path(frames).stem if frames else "demo"
    if frames and input_identity(frames).startswith("upload:"):
        stem = Path(frames).stem.split("-", 2)[-1]
    stem = "".join(c if c.isalnum() or c in "-_" else "_" for c in stem)[:40] or "input"
    return Path(data_dir) / "projects" / f"{stem}-{hashlib.sha1(key).hexdigest()[:10]}"


# Of the sanitised name an upload keeps: file systems allow 255 bytes a name, and the kind and
# hash come first.
UPLOAD_NAME_CHARS = 120


def upload_name(kind: str, filename: str, content: bytes) -> str:
    """The stored name of an upload: kind, a hash of its content, the sanitised file name
    (its stem shortened to fit ``UPLOAD_NAME_CHARS`` with its suffix)."""
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in Path(filename).name)
    safe = safe.lstrip(".") or "upload"
    if len(safe) > UPLOAD_NAME_CHARS:
        suffix = Path(safe).suffix[:16]
        safe = safe[: UPLOAD_NAME_CHARS - len(suffix)] + suffix
    return f"{kind}-{hashlib.sha1(content).hexdigest()[:10]}-{safe}"


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
        return self.folder / UPLOADS

    def adopt_upload(self, path: str) -> str:
        """A file uploaded into another project's uploads, given to this one too: a hard link
        (a copy across file systems) in this project's uploads, so that each project keeps
        its inputs whatever the other prunes; the other project's file stays where it is.
        Returns the (possibly new) path; other paths are returned unchanged."""
        p = Path(path)
        if not input_identity(path).startswith("upload:") or p.parent == self.uploads_dir:
            return path
        target = self.uploads_dir / p.name
        self.uploads_dir.mkdir(parents=True, exist_ok=True)
        if not target.exists():
            try:
                os.link(p, target)
            except OSError:
                shutil.copy2(p, target)
        return str(target)

    def prune_uploads(self, keep: list[str]) -> list[Path]:
        """Delete uploaded files that none of ``keep`` (the open inputs' paths) refers to;
        returns the deleted paths."""
        folder = self.uploads_dir
        if not folder.is_dir():
            return []
        kept = set()
        for k in keep:
            try:
                kept.add(Path(k).resolve())
            except (OSError, RuntimeError):
                continue
        removed = []
        for f in folder.iterdir():
            # Dot files are uploads being written (write_atomic's temporaries).
            if f.is_file() and not f.name.startswith(".") and f.resolve() not in kept:
                f.unlink(missing_ok=True)
                removed.append(f)
        return removed

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
        (self.folder / RESULT_FIT).unlink(missing_ok=True)  # the next run records its own
        return target

    def read_result_fit(self) -> str | None:
        """The reference-fit edits the project's result was made with (None: not recorded)."""
        path = self.folder / RESULT_FIT
        try:
            return json.loads(path.read_text())["edits"]
        except (OSError, ValueError, KeyError, TypeError):
            return None

    def write_result_fit(self, edits: str) -> None:
        """Record which reference-fit edits the project's result is made with."""
        write_atomic(self.folder / RESULT_FIT, json.dumps({"edits": edits}) + "\n")

    def earlier_results(self) -> list[Path]:
        """The results moved aside by :meth:`archive_result`, oldest first."""
        found = []
        for p in self.folder.glob("result.prev-*"):
            suffix = p.name.rsplit("-", 1)[1]
            if p.is_dir() and suffix.isdigit():
                found.append((int(suffix), p))
        return [p for _, p in sorted(found)]

    def restore_result(self, earlier: Path) -> Path | None:
        """Make ``earlier`` (one of :meth:`earlier_results`) the project's result again; the
        current result, if any, is moved aside first. Returns where it went (or None)."""
        if earlier not in self.earlier_results():
            raise ValueError(f"{earlier.name} is not an earlier result of this project")
        kept = self.archive_result() if self.result_dir.exists() else None
        os.replace(earlier, self.result_dir)
        (self.folder / RESULT_FIT).unlink(missing_ok=True)  # unknown: continued as it is
        return kept

    def write_file(self, name: str, data: bytes | str) -> Path:
        path = self.folder / name
        write_atomic(path, data)
        return path


REFERENCE_FILE = "reference.npz"
RESULT_FIT = "result_fit.json"
"""Which reference-fit edits the project's result was made with."""


def reference_to_bytes(key: dict, coarse, fine) -> bytes:
    """The Seed view's coarse and fine results (``global_registration.CoarseResult`` /
    ``FineResult``, fine may be None) as npz bytes, with ``key`` (γ, seed, reference frame, preset)
    recorded so a stale file is never restored for other settings."""
    import io as _io

    import numpy as np

    def model_json(m) -> str:
        return json.dumps(m.to_dict()) if m is not None else ""

    arrays = {
        "key": np.array(json.dumps(key, sort_keys=True)),
        "c_meta": np.array(
            json.dumps(
                {
                    "success": bool(coarse.success),
                    "reason": coarse.reason,
                    "n_keypoints_frame": int(coarse.n_keypoints_frame),
                    "n_keypoints_base": int(coarse.n_keypoints_base),
                    "gate_radius_base": coarse.gate_radius_base,
                    "gate_center_base": None
                    if coarse.gate_center_base is None
                    else [float(v) for v in coarse.gate_center_base],
                    "time_s": float(coarse.time_s),
                    "model": model_json(coarse.base_from_corrected),
                    # What the seeding shows (heading, scale, the gate used), not only the model.
                    "heading_deg": _float_or_none(coarse.heading_deg),
                    "scale": _float_or_none(coarse.scale),
                    "gate": coarse.gate,
                    "model_kind": coarse.model_kind,
                    "ambiguity": _float_or_none(coarse.ambiguity),
                    "seeds": [list(map(float, s)) for s in coarse.seeds],
                }
            )
        ),
        "c_frame_xy": coarse.frame_xy,
        "c_base_xy": coarse.base_xy,
        "c_gated": coarse.gated,
        "c_inliers": coarse.inliers,
    }
    if coarse.gate_outline_base is not None:
        arrays["c_gate_outline"] = np.asarray(coarse.gate_outline_base, np.float64)
    if fine is not None:
        arrays["f_meta"] = np.array(
            json.dumps(
                {
                    "success": bool(fine.success),
                    "reason": fine.reason,
                    "iterations": int(fine.iterations),
                    "time_s": float(fine.time_s),
                    "model": model_json(fine.base_from_corrected),
                    "model_kind": fine.model_kind,
                    "model_reason": fine.model_reason,
                    "click_note": fine.click_note,
                }
            )
        )
        arrays.update(f_src=fine.src, f_dst=fine.dst, f_kept=fine.kept, f_residuals=fine.residuals)
        if fine.source is not None:
            arrays["f_source"] = np.asarray(fine.source)
    buf = _io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def _float_or_none(v) -> float | None:
    return None if v is None else float(v)


def reference_from_file(path: Path):
    """``(key, coarse, fine)`` read back from :func:`reference_to_bytes`'s file, or None when the
    file is missing or unreadable (it is a cache of recomputable results)."""
    import numpy as np

    from registration.geometry import model_from_dict
    from registration.global_registration import CoarseResult, FineResult

    def model(text: str):
        return model_from_dict(json.loads(text)) if text else None

    try:
        with np.load(path) as z:
            a = {k: z[k] for k in z.files}
        key = json.loads(str(a["key"]))
        cm = json.loads(str(a["c_meta"]))
        coarse = CoarseResult(
            success=cm["success"],
            reason=cm["reason"],
            base_from_corrected=model(cm["model"]),
            frame_xy=a["c_frame_xy"],
            base_xy=a["c_base_xy"],
            gated=a["c_gated"].astype(bool),
            inliers=a["c_inliers"].astype(bool),
            n_keypoints_frame=cm["n_keypoints_frame"],
            n_keypoints_base=cm["n_keypoints_base"],
            gate_center_base=None
            if cm["gate_center_base"] is None
            else np.asarray(cm["gate_center_base"], float),
            gate_radius_base=cm["gate_radius_base"],
            time_s=cm["time_s"],
            heading_deg=cm.get("heading_deg"),
            scale=cm.get("scale"),
            gate=cm.get("gate", ""),
            gate_outline_base=a.get("c_gate_outline"),
            model_kind=cm.get("model_kind", "projective"),
            ambiguity=cm.get("ambiguity"),
            seeds=tuple(tuple(map(float, s)) for s in cm.get("seeds", [])),
        )
        fine = None
        if "f_meta" in a:
            fm = json.loads(str(a["f_meta"]))
            fine = FineResult(
                success=fm["success"],
                reason=fm["reason"],
                base_from_corrected=model(fm["model"]),
                src=a["f_src"],
                dst=a["f_dst"],
                kept=a["f_kept"].astype(bool),
                residuals=a["f_residuals"],
                iterations=fm["iterations"],
                time_s=fm["time_s"],
                source=a.get("f_source"),
                model_kind=fm.get("model_kind", "polyprojective"),
                model_reason=fm.get("model_reason", ""),
                click_note=fm.get("click_note", ""),
            )
    except (OSError, ValueError, KeyError, TypeError, json.JSONDecodeError):
        return None
    return key, coarse, fine
