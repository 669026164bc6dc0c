"""One error type for everything a user can get wrong: it names the file and the problem;
`exit_code` is how the commands report it."""
import sys


class FlowBSDFError(Exception):
    """Bad input or a failed operation, with a message fit for the user (no traceback needed)."""

    def __init__(self, problem: str, path=None):
        self.path = None if path is None else str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path else problem)


def exit_code(call, prog, interrupted="interrupted"):
    """Run call(): 0, or 2 after printing a FlowBSDFError as `prog: error: ...` (no traceback),
    or 130 after printing `prog: <interrupted>` on Ctrl-C."""
    try:
        call()
    except FlowBSDFError as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: {interrupted}", file=sys.stderr)
        return 130
    return 0
