"""Command-line options from a TOML file: ``face-dolfinx SUBCOMMAND --config run.toml``.

Any option of the command line can be set in the file, under its long name with dashes or
underscores (``gn-steps`` or ``gn_steps``); positional arguments too, under their name
(``capture``, ``expressions``). Keys at the top level are shared: they apply to every subcommand
that has such an option (and are checked to be an option of at least one). A table named after a
subcommand (``[fit]``, ``[build]``, ...) applies to that subcommand only and overrides the
top-level keys. Flags given on the command line override the file. See docs/cli.md.

The whole file is checked, tables of other subcommands included, so that a misspelt key is never
silently ignored: an unknown key, an unknown table or a value of the wrong type raises
ConfigError naming the file, the table and the key.
"""
from __future__ import annotations

import argparse
import difflib
import math
import tomllib
from pathlib import Path

# Options that make no sense in a file: the file itself, and help.
NOT_CONFIGURABLE = {"config", "help"}


class ConfigError(ValueError):
    """A configuration file that can't be used; the message names the file, table and key."""


def read_config(path) -> dict:
    """The TOML file as a dict; a missing, unreadable or malformed file raises ConfigError."""
    path = Path(path)
    if path.suffix.lower() != ".toml":
        raise ConfigError(f"{path}: a configuration file must be TOML (.toml), not {path.suffix or 'without a suffix'}")
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such configuration file") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not UTF-8 text") from None
    except tomllib.TOMLDecodeError as error:  # its message gives the line and column
        raise ConfigError(f"{path}: malformed TOML: {error}") from None


def option_defaults(path, command: str, main_parser: argparse.ArgumentParser,
                    subparsers: dict[str, argparse.ArgumentParser]) -> tuple[dict, dict]:
    """(defaults for the main parser, defaults for ``command``'s parser) from the file at ``path``.

    Each is {dest: value}, to be given to ``set_defaults`` before parsing the command line again,
    so that explicit flags win.
    """
    path = Path(path)
    data = read_config(path)
    main_options = _options(main_parser)
    command_options = {name: _options(parser) for name, parser in subparsers.items()}

    tables = {key: value for key, value in data.items() if isinstance(value, dict)}
    for key in tables:
        if key not in subparsers:
            raise ConfigError(f"{path}: unknown table [{key}]{_suggest(key, subparsers)}; tables are "
                              f"subcommands: {', '.join(f'[{name}]' for name in subparsers)}")
    shared = _by_name({key: value for key, value in data.items() if key not in tables}, path, None)

    main_defaults, command_defaults = {}, {}
    for name, (key, value) in shared.items():
        owners = [command for command, options in command_options.items() if name in options]
        if name in main_options:
            main_defaults[main_options[name].dest] = _checked(main_options[name], value, path, key, None)
        elif not owners:
            every = sorted(set(main_options).union(*command_options.values()))
            raise ConfigError(f"{path}: unknown key {key!r}{_suggest(name, every)} (not an option of any "
                              f"subcommand)")
        for owner in owners:  # checked for every subcommand that has it, used for this one
            checked = _checked(command_options[owner][name], value, path, key, None)
            if owner == command:
                command_defaults[command_options[owner][name].dest] = checked
    for table, entries in tables.items():
        options = command_options[table]
        for name, (key, value) in _by_name(entries, path, table).items():
            if name not in options:
                raise ConfigError(f"{path}: unknown key {key!r} in [{table}]{_suggest(name, options)}; "
                                  f"{table} takes: {', '.join(sorted(options))}")
            checked = _checked(options[name], value, path, key, table)
            if table == command:
                command_defaults[options[name].dest] = checked
    return main_defaults, command_defaults


def _options(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    """{canonical name: action} for the options and positionals a file may set."""
    options = {}
    for action in parser._actions:  # argparse has no public list of a parser's arguments
        if isinstance(action, argparse._SubParsersAction):
            continue
        long_names = [s[2:] for s in action.option_strings if s.startswith("--")]
        name = long_names[0] if long_names else (action.dest if not action.option_strings else None)
        if name is not None and _canonical(name) not in NOT_CONFIGURABLE:
            options[_canonical(name)] = action
    return options


def _by_name(entries: dict, path: Path, table: str | None) -> dict[str, tuple[str, object]]:
    """{canonical name: (key as written, value)}; one option spelt two ways is an error."""
    named = {}
    for key, value in entries.items():
        name = _canonical(key)
        if name in named:
            where = "the top level" if table is None else f"[{table}]"
            raise ConfigError(f"{path}: {where} sets {name!r} twice ({named[name][0]!r} and {key!r})")
        named[name] = (key, value)
    return named


def _canonical(key: str) -> str:
    return key.strip().replace("_", "-")


def _checked(action: argparse.Action, value, path: Path, key: str, table: str | None):
    """The value converted as the command line would, or a ConfigError saying what is expected."""
    where = f"{path}: {'' if table is None else f'[{table}] '}{key}"
    if action.nargs == 0:  # a flag (store_true)
        if not isinstance(value, bool):
            raise ConfigError(f"{where} must be true or false, not {value!r}")
        return value
    if action.nargs in ("*", "+"):
        if not isinstance(value, list) or (action.nargs == "+" and not value):
            raise ConfigError(f"{where} must be a list{' of at least one value' if action.nargs == '+' else ''}, "
                              f"not {value!r}")
        return [_single(action, item, where) for item in value]
    return _single(action, value, where)


def _single(action: argparse.Action, value, where: str):
    kind = action.type
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where} must be an integer, not {value!r}")
    elif kind is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ConfigError(f"{where} must be a number, not {value!r}")
        value = float(value)
    elif kind is not None and kind is not str:  # an option's own parser, e.g. a number or a word
        if isinstance(value, bool) or not isinstance(value, (int, float, str)):
            raise ConfigError(f"{where} must be a number or a word, not {value!r}")
        try:
            value = kind(str(value))
        except argparse.ArgumentTypeError as error:
            raise ConfigError(f"{where}: {error}") from None
    elif not isinstance(value, str):
        raise ConfigError(f"{where} must be a string, not {value!r}")
    if action.choices is not None and value not in action.choices:
        raise ConfigError(f"{where} = {value!r}: expected one of {', '.join(map(str, action.choices))}")
    return value


def _suggest(name: str, known) -> str:
    close = difflib.get_close_matches(name, list(known), n=2, cutoff=0.6)
    return f" (did you mean {' or '.join(repr(c) for c in close)}?)" if close else ""
