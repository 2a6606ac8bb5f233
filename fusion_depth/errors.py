"""The errors the package raises about a user's input. Each is a line naming the key, file or
value and what it may be; the commands print it as its message alone (no traceback, unless
``HYDRA_FULL_ERROR=1``; :mod:`fusion_depth.config.hydra_main`). They still are the built-in
error types, so callers can catch ValueError / OSError / ImportError. This module imports only
the standard library: the science packages raise these without knowing of Hydra, naming their
arguments (:class:`ArgumentError`), which the commands report as config keys."""

from __future__ import annotations

from collections.abc import Callable, Sequence


class UserError(Exception):
    """An error about the user's input (data, config value, file), shown as its message alone."""


class ConfigError(ValueError, UserError):
    """A config value or key that cannot work; the one-line message names the key and what is
    allowed."""


class MissingDependencyError(ImportError, UserError):
    """The chosen dataset, export format or engine needs a package that is not installed, or a
    device that is not there (a CUDA GPU for TensorRT)."""


class OutputDirError(OSError, UserError):
    """The output directory cannot be written, or has too little free space."""


class CommandError(RuntimeError, UserError):
    """A user-facing error (bad data, config value or file) shown as its message alone; the
    original exception is its ``__cause__`` (shown with ``HYDRA_FULL_ERROR=1``)."""


class ArgumentError(ValueError, UserError):
    """A value a science function or class cannot take, naming its argument, not a config key:
    the science packages know no config. The commands report it naming where the user set it
    (:func:`fusion_depth.config.arguments.config_message`: ``weights`` → ``backbone.weights``).

    Args:
        message: the message, each argument it names written ``{name}``:
            ``f"{{weights}}={weights}: no such file"``.
        arguments: the arguments it names.
        owner: the function or class that takes them, or its dotted name: the config layer
            looks up where its arguments come from by it.

    A subclass keeps this signature (pickling rebuilds it through it).
    """

    def __init__(self, message: str, *arguments: str, owner: object) -> None:
        self.template, self.arguments = message, arguments
        self.owner = owner if isinstance(owner, str) else f"{owner.__module__}.{owner.__qualname__}"
        super().__init__(self.naming(str))

    def naming(self, key: Callable[[str], str]) -> str:
        """The message with each argument named ``key(argument)``."""
        message = self.template
        for name in self.arguments:
            message = message.replace("{" + name + "}", key(name))
        return message

    def __reduce__(self) -> tuple:
        # Pickled whole (a worker process hands it back): __init__ does not take args alone.
        return (_restore, (type(self), self.template, self.arguments, self.owner))


def _restore(
    cls: type[ArgumentError], template: str, arguments: tuple[str, ...], owner: str
) -> ArgumentError:
    return cls(template, *arguments, owner=owner)


class ArgumentFileError(ArgumentError, FileNotFoundError):
    """An :class:`ArgumentError` about a file that is not there (still a FileNotFoundError)."""


def check_choice(value: object, allowed: Sequence[object], argument: str, *, owner: object) -> None:
    """Refuse ``value`` unless it is one of ``allowed``.

    Raises:
        ArgumentError: ``{argument}={value!r}: expected one of [...]``, about ``owner``'s
            ``argument``.
    """
    if value not in allowed:
        raise ArgumentError(
            f"{{{argument}}}={value!r}: expected one of {list(allowed)}", argument, owner=owner
        )
