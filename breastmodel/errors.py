"""The one error type the pipeline raises for user-facing failures."""


class StageError(RuntimeError):
    """A clear failure that names the stage, the file and the problem."""

    def __init__(self, stage: str, message: str, path=None):
        where = f" [{path}]" if path is not None else ""
        super().__init__(f"{stage}{where}: {message}")
        self.stage, self.path, self.message = stage, path, message
