"""One error hierarchy for the project; messages name the file, part or value that was wrong."""


class PartInstructError(Exception):
    """Base class of every error raised on purpose by partinstruct_mjx."""


class AssetError(PartInstructError):
    """A robot or object asset is missing, unreadable or malformed."""


class SceneError(PartInstructError):
    """A scene cannot be assembled or a backend was given inconsistent input."""


class TaskError(PartInstructError):
    """A task, skill, part, direction or episode is unknown, malformed or impossible."""


class DataError(PartInstructError):
    """Demonstration data is malformed, duplicated, or inconsistent with the run directory it is written to."""


class EvalError(PartInstructError):
    """An evaluation was asked for with bad settings, a missing policy, or a run directory made with others."""
