"""User-input errors: one sentence naming the input and what was expected, then a non-zero exit.

`InputError` is a SystemExit, so a command line prints only the sentence (no traceback) and exits with
status 1, while library callers and tests can still catch the specific subclass.
"""


class InputError(SystemExit):
    """An input (file, flag, dataset, checkpoint) that cannot be used as given."""

    def __init__(self, message: str):
        super().__init__(message)
        self.message = message

    def __str__(self) -> str:
        return self.message
