"""One exception hierarchy for mmpa. Every message names the problem and, where it helps,
the valid alternatives, so a user can fix the input without reading the source."""

from __future__ import annotations


class MMPAError(Exception):
    """Base class of every error mmpa raises on purpose."""


class InvalidInputError(MMPAError, ValueError):
    """An argument is malformed: wrong shape, NaN, out of range."""


class ConfigError(MMPAError, ValueError):
    """A configuration or scene file is malformed; the message names the field."""


class UnknownNameError(MMPAError, KeyError):
    """A named thing (site, object, task) does not exist; the message lists the valid names."""

    def __init__(self, kind: str, name: str, valid: list[str] | tuple[str, ...]) -> None:
        self.kind, self.name, self.valid = kind, name, list(valid)
        super().__init__(f"unknown {kind} {name!r}; valid: {', '.join(map(str, valid))}")

    def __str__(self) -> str:  # KeyError would otherwise quote the whole message
        return str(self.args[0])


class UnreachableError(MMPAError):
    """A pose cannot be reached by the arm (no IK solution within joint limits)."""


class SimulationError(MMPAError):
    """The simulator failed (unstable physics, rendering unavailable)."""


class TaskNotFoundError(UnknownNameError):
    """A task is not in the store; the message names the store and the stored tasks."""

    def __init__(self, name: str, valid: list[str] | tuple[str, ...], where: str = "") -> None:
        self.kind, self.name, self.valid = "task", name, list(valid)
        shown = ", ".join(map(str, self.valid[:20])) + (" ..." if len(self.valid) > 20 else "")
        msg = f"no task {name!r}" + (f" in {where}" if where else "")
        msg += f"; stored: {shown}" if self.valid else "; the store is empty"
        KeyError.__init__(self, msg)


class CorruptTaskError(MMPAError):
    """A stored task or bundle fails its checks (checksum, size, missing field or file)."""


class UnsupportedVersionError(MMPAError):
    """A task store or bundle was written by a newer mmpa (schema or format version)."""


class TaskExistsError(MMPAError, ValueError):
    """Saving or importing a task whose name is taken, without ``overwrite``."""


class JointLimitError(MMPAError, ValueError):
    """A joint command or path breaks the arm's position, velocity or acceleration limits;
    refused before anything moves."""
