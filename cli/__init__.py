"""The ``forensics`` command (installed as ``forensics.cli``; source in ``cli/``).

One module per command (``simulate``, ``fingerprint``, ``defects`` …), each with ``register(subparsers)``;
``main`` builds the parser and runs a command (the console entry point is ``forensics.cli.main:main``);
``common`` holds the shared options, option types, the input/output guard and :func:`emit`; ``errors`` maps
every exception to one line and an exit code.  Nothing here does science: handlers call the library.
"""
import lazy_loader as _lazy

# Public names load their module on first use: ``import forensics.cli`` alone imports no command.  (The
# function ``main`` is not listed here: its name is the module's, forensics.cli.main.)
__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    submod_attrs={
        "main": ["COMMAND_MODULES", "build_parser"],
        "common": [
            "EXIT_BAD_INPUT", "EXIT_FAILURE", "EXIT_INTERRUPTED", "EXIT_OK", "EXIT_USAGE", "declared_paths", "emit",
            "guard_outputs", "say",
        ],
        "errors": ["describe"],
    },
)
