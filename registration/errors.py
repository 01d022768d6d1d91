"""The library's errors about what a user gave it or asked of it.

Each says what is wrong in one line, in words of no front end (no command-line flag, no button),
and carries the facts as attributes (which folder, which frame, what differs), so that the
command line and the browser app can each add what the user can do in their own words: the CLI
names its flags (:func:`app.cli` phrases them), the app its buttons. ``remedy`` names that
advice, one of :data:`REMEDIES`.

All are ``ValueError``: unusable input, as the library raised before they had types.
"""

from __future__ import annotations

from pathlib import Path

# What the user can do about an error, named once for every front end.
REMEDIES = {
    "": "nothing to add",
    "another_folder": "choose another (new or empty) output folder",
    "continue_or_restart": "continue the result, start over, or choose another output folder",
    "restart": "start over, or choose another output folder",
    "wait": "wait for the other process, or choose another output folder",
    "another_reference_frame": "choose another reference frame",
    "georeference": "give the base map's georeference",
    "overwrite": "allow overwriting, or choose another output folder",
    "resume": "resume the registration, which redoes them",
    "click": "click one corresponding point in the frame and the map",
}


class AerialregError(ValueError):
    """Base of the library's typed errors (module docstring)."""

    remedy: str = ""


class ResultFolderError(AerialregError):
    """A result folder cannot be written or read as asked."""

    def __init__(self, message: str, out_dir: str | Path) -> None:
        super().__init__(message)
        self.out_dir = Path(out_dir)


class NotAFolder(ResultFolderError):
    """The output path is a file."""

    remedy = "another_folder"

    def __init__(self, out_dir: str | Path) -> None:
        super().__init__(f"{out_dir} exists and is a file, not a folder", out_dir)


class ForeignFolder(ResultFolderError):
    """The output folder holds files that are not a registration result's."""

    remedy = "another_folder"

    def __init__(self, out_dir: str | Path, example: str) -> None:
        super().__init__(
            f"{out_dir} is not an aerialreg result folder (it holds e.g. {example!r})", out_dir
        )
        self.example = example


class ResultExists(ResultFolderError):
    """The output folder already holds a result, and neither resuming nor starting over was
    asked."""

    remedy = "continue_or_restart"

    def __init__(self, out_dir: str | Path) -> None:
        super().__init__(f"{out_dir} already holds a registration result", out_dir)


class ResultDamaged(ResultFolderError):
    """The output folder holds a result whose ``result.json`` is missing or corrupt."""

    remedy = "restart"

    def __init__(self, out_dir: str | Path, *, resuming: bool) -> None:
        what = f"cannot resume {out_dir}: it holds" if resuming else f"{out_dir} holds"
        super().__init__(
            f"{what} a damaged registration result (result.json missing or corrupt)", out_dir
        )
        self.resuming = resuming


class ResumeMismatch(ResultFolderError):
    """A resume was asked with other inputs or settings than the result was made with."""

    remedy = "restart"

    def __init__(self, out_dir: str | Path, difference: str, key: str | None = None) -> None:
        super().__init__(f"cannot resume {out_dir}: {difference}", out_dir)
        self.difference = difference
        self.key = key  # the result.json key that differs (None: the inputs' files)


class ResultBusy(ResultFolderError):
    """Another process is writing the result folder."""

    remedy = "wait"

    def __init__(self, out_dir: str | Path, holder: str) -> None:
        super().__init__(
            f"{out_dir} is being written by another aerialreg process ({holder})", out_dir
        )
        self.holder = holder


class NotGeoreferenced(ResultFolderError):
    """Map coordinates or a map format were asked of a result whose base map is a plain
    image."""

    remedy = "georeference"


class FilesExist(ResultFolderError):
    """Files an export would write exist already."""

    remedy = "overwrite"

    def __init__(self, first: str | Path, n_existing: int, n_files: int) -> None:
        super().__init__(
            f"{first} exists ({n_existing} of the {n_files} files to write)", Path(first).parent
        )
        self.first = Path(first)


class ReferenceFrameUnusable(AerialregError):
    """The reference frame cannot start a run (unreadable, or another size than the
    sequence)."""

    remedy = "another_reference_frame"

    def __init__(self, message: str, frame: int) -> None:
        super().__init__(message)
        self.frame = frame


class RegistrationFailed(AerialregError):
    """The reference frame could not be registered to the base map, so no frame can be.

    ``remedy`` is ``"click"`` where a seed click would help (the coarse step found no heading
    and scale on its own)."""

    def __init__(self, message: str, frame: int, *, remedy: str = "") -> None:
        super().__init__(message)
        self.frame = frame
        self.remedy = remedy
