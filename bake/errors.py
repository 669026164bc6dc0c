"""One error type for everything a user can get wrong: it names the file and the problem."""


class FlowBSDFError(Exception):
    """Bad input or a failed operation, with a message fit for the user (no traceback needed)."""

    def __init__(self, problem: str, path=None):
        self.path = None if path is None else str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path else problem)
