"""Command-line options generated from frozen dataclasses and their field docstrings.

Every parameter of the pipeline lives in one frozen dataclass per stage with a docstring under
each field (``DecompositionParams``, ``SamplingParams``, ...). An :class:`Options` turns such a
dataclass into one argparse group -- flag, type, default and help all read from the field -- and
builds the dataclass back from the parsed namespace. A ``ValueError`` of the dataclass's
``__post_init__`` that names a field becomes an :class:`OptionError` naming the flag instead
(``--mu: must be a finite number >= 0, got -1.0``), which the CLI prints as one line (exit 2).

Generated, per field (the type comes from the annotation):

=================================== =====================================================
field type                          option
=================================== =====================================================
``int``, ``float``, ``str``         ``--name VALUE`` (``str`` may take ``Flag.choices``)
``Literal["a", "b"]``               ``--name {a,b}``
``float | None`` (default ``None``) ``--name VALUE``, unset by default
``bool``                            ``--name`` / ``--no-name``
``tuple[float, float, float]``      ``--name X Y Z``
an ``enum.Enum``                    ``--name {value,...}``
a nested dataclass                  its own group (``Options.nested``)
=================================== =====================================================

The flag is ``--`` + the field name with dashes unless :class:`Flag` says otherwise (today's
spellings such as ``--cone-edges`` for ``QualityParams.n_edges``). The help is the field's
docstring in plain text (reST roles and literals dropped; a literal naming another field of the
same dataclass becomes that field's flag), followed by the default.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import enum
import inspect
import re
import textwrap
import types
import typing
from collections.abc import Mapping
from typing import Any, Generic, TypeVar

from pregrasp_core.errors import PregraspError

T = TypeVar("T")


class OptionError(PregraspError):
    """A command-line value that the parameter dataclass rejects; the message names the flag."""


@dataclasses.dataclass(frozen=True)
class Flag:
    """How one field appears on the command line: only what differs from the generated option."""

    name: str | tuple[str, ...] | None = None
    """The option strings, e.g. ``"--cone-edges"`` or ``("-o", "--output")``; ``None`` =
    ``--`` + the field name with dashes (``--no-`` + it as well for a ``bool``)."""
    metavar: str | tuple[str, ...] | None = None
    """The value's name in ``--help``; ``None`` = ``M`` for a length in metres (the docstring
    says metres), ``N`` for an integer, ``F`` for another number, ``S`` for text."""
    choices: tuple[str, ...] | None = None
    """Allowed values of a ``str`` field (an enum field lists its values by itself)."""
    store_true: bool = False
    """A ``bool`` field that defaults to ``False`` and is set by the flag alone (no ``--no-``
    form), such as ``--include-indices``."""
    help: str | None = None
    """Help text instead of the docstring, where the docstring speaks of code rather than of
    the command line (a module docstring, a Python constant)."""


def field_docs(cls: type[Any]) -> dict[str, str]:
    """Name -> docstring (the string literal right below it) of the fields of dataclass ``cls``,
    or of the members of enum ``cls``."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    body = next(n for n in tree.body if isinstance(n, ast.ClassDef)).body
    docs: dict[str, str] = {}
    for stmt, nxt in zip(body, body[1:], strict=False):
        target: ast.expr
        if isinstance(stmt, ast.AnnAssign):
            target = stmt.target
        elif isinstance(stmt, ast.Assign) and len(stmt.targets) == 1:
            target = stmt.targets[0]
        else:
            continue
        if (
            isinstance(target, ast.Name)
            and isinstance(nxt, ast.Expr)
            and isinstance(nxt.value, ast.Constant)
            and isinstance(nxt.value.value, str)
        ):
            docs[target.id] = inspect.cleandoc(nxt.value.value)
    return docs


class HelpFormatter(argparse.HelpFormatter):
    """argparse's formatter without breaking lines inside a hyphenated word (a flag such as
    ``--closing-margin`` in a help text stays whole)."""

    def _split_lines(self, text: str, width: int) -> list[str]:
        text = " ".join(text.split())
        return textwrap.wrap(text, width, break_on_hyphens=False)


def _plain(doc: str, words: Mapping[str, str]) -> str:
    """A docstring as one line of plain help text: reST roles and literals as plain words, a
    literal in ``words`` (another field's name, ``None``...) replaced by its value there."""
    text = " ".join(doc.split())
    # :class:`~pkg.Name` -> Name; ``field`` -> its flag; ``literal`` -> literal
    text = re.sub(r":\w+:`~?([^`]+)`", lambda m: m.group(1).rsplit(".", 1)[-1], text)
    return re.sub(r"``([^`]+)``", lambda m: words.get(m.group(1), m.group(1)), text)


def _shown(value: object) -> str:
    """A default as a user types it."""
    if isinstance(value, enum.Enum):
        return str(value.value)
    if isinstance(value, tuple):
        return " ".join(_shown(v) for v in value)
    return str(value)


def _unwrap_optional(tp: Any) -> tuple[Any, bool]:
    """(``X``, True) for ``X | None``, else (``tp``, False)."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1 and len(typing.get_args(tp)) == 2:
            return args[0], True
    return tp, False


class Options(Generic[T]):
    """The command-line options of one dataclass (and of the dataclasses nested in it).

    cls: a dataclass whose fields all have defaults. title: the ``--help`` group; ``None`` = no
    group of its own (a dataclass holding only nested ones, like ``PipelineParams``). dest: a
    prefix that keeps the namespace entries of this dataclass apart from others'
    (``planner.quality.mu``). flags: field name -> :class:`Flag` where the option differs from the
    generated one. fields: the fields offered (default: every field not nested); the others keep
    their defaults. nested: field name -> the :class:`Options` of a nested dataclass field, added
    after this one's group.
    """

    def __init__(
        self,
        cls: type[T],
        title: str | None,
        dest: str,
        flags: Mapping[str, Flag] | None = None,
        fields: tuple[str, ...] | None = None,
        nested: Mapping[str, Options[Any]] | None = None,
    ) -> None:
        if not dataclasses.is_dataclass(cls):
            raise TypeError(f"{cls!r} is not a dataclass")
        self.cls = cls
        self.title = title
        self.dest = dest
        self.nested: dict[str, Options[Any]] = dict(nested or {})
        names = [f.name for f in dataclasses.fields(cls)]
        flags = dict(flags or {})
        unknown = sorted((set(flags) | set(self.nested) | set(fields or ())) - set(names))
        if unknown:
            raise ValueError(f"{cls.__name__} has no field {', '.join(unknown)}")
        self.fields = tuple(fields) if fields is not None else tuple(
            n for n in names if n not in self.nested
        )  # fmt: skip
        self.flags = {n: flags.get(n, Flag()) for n in self.fields}
        self._hints = typing.get_type_hints(cls)
        self._defaults = cls()  # every field has a default
        self._docs = field_docs(cls)

    # ---------------------------------------------------------------- naming
    def option_strings(self, name: str) -> tuple[str, ...]:
        """The option strings of field ``name`` (``--no-x`` of a bool is added by argparse)."""
        given = self.flags[name].name
        if given is None:
            return ("--" + name.replace("_", "-"),)
        return (given,) if isinstance(given, str) else tuple(given)

    def flag(self, name: str) -> str:
        """The main (longest) flag of field ``name``."""
        return max(self.option_strings(name), key=len)

    def flag_of_field(self) -> dict[str, str]:
        """Field name -> flag, of this dataclass's offered fields."""
        return {n: self.flag(n) for n in self.fields}

    def _key(self, name: str) -> str:
        return f"{self.dest}.{name}"

    # ---------------------------------------------------------------- argparse
    def add_to(
        self, parser: argparse.ArgumentParser, group: argparse._ArgumentGroup | None = None
    ) -> None:
        """Register the options: in ``group`` if given, else in a group of their own titled as
        given; the nested dataclasses' after them, each in its own group."""
        if self.fields:
            g = group if group is not None else parser.add_argument_group(self.title)
            for name in self.fields:
                self._add(g, name)
        for sub in self.nested.values():
            sub.add_to(parser)

    def help_text(self, name: str) -> str:
        """The ``--help`` text of field ``name`` (without its default)."""
        spec = self.flags[name]
        if spec.help is not None:
            return spec.help
        tp, _ = _unwrap_optional(self._hints[name])
        words = self.flag_of_field()
        if tp is bool:
            words.update({"True": self.flag(name), "False": "--no-" + self.flag(name)[2:]})
        if getattr(self._defaults, name) is None:
            words["None"] = "not given"
        doc = self._docs.get(name, "")
        if isinstance(tp, type) and issubclass(tp, enum.Enum):
            # "(:class:`Policy` or its string value)" speaks of Python: the members instead
            doc = re.sub(rf"\s*\(:class:`~?[\w.]*{tp.__name__}`[^)]*\)", "", doc)
            members = field_docs(tp)
            doc += "".join(f" {m.value}: {members.get(m.name, '')}" for m in tp)
        text = _plain(doc, words)
        if getattr(self._defaults, name) is None:
            text = re.sub(r"\bNone\b", "not given", text)
        return text

    def _add(self, g: argparse._ArgumentGroup, name: str) -> None:
        spec = self.flags[name]
        tp, _ = _unwrap_optional(self._hints[name])  # None only as the default: never typed
        default = getattr(self._defaults, name)
        help_text = self.help_text(name)
        kw: dict[str, Any] = {"dest": self._key(name), "default": default}
        if tp is bool:
            if spec.store_true:
                if default:
                    raise ValueError(f"{self.cls.__name__}.{name}: store_true needs default False")
                kw["action"] = "store_true"
            else:
                kw["action"] = argparse.BooleanOptionalAction
                on = self.flag(name)
                help_text += f" (default: {on if default else '--no-' + on[2:]})"
            g.add_argument(*self.option_strings(name), help=help_text.replace("%", "%%"), **kw)
            return
        if default is not None:
            help_text += f" (default: {_shown(default)})"
        help_text = help_text.replace("%", "%%")
        if isinstance(tp, type) and issubclass(tp, enum.Enum):
            kw.update(choices=[str(m.value) for m in tp], default=str(default.value))
        elif typing.get_origin(tp) is tuple:
            args = typing.get_args(tp)
            if Ellipsis in args or len(set(args)) != 1:
                raise TypeError(f"{self.cls.__name__}.{name}: only tuple[X, X, ...] of one type")
            kw.update(type=args[0], nargs=len(args))
            if default is not None:
                kw["default"] = list(default)
        elif typing.get_origin(tp) is typing.Literal:
            values = typing.get_args(tp)
            kw.update(type=type(values[0]), choices=list(values))
        elif tp in (int, float, str):
            kw["type"] = tp
            if spec.choices is not None:
                kw["choices"] = list(spec.choices)
        else:
            raise TypeError(f"{self.cls.__name__}.{name}: no option for type {tp!r}")
        if "choices" not in kw:
            kw["metavar"] = spec.metavar or self._metavar(name, kw.get("type"))
        g.add_argument(*self.option_strings(name), help=help_text, **kw)

    def _metavar(self, name: str, tp: Any) -> str | tuple[str, ...]:
        nargs = typing.get_args(_unwrap_optional(self._hints[name])[0])
        if nargs:
            return tuple("XYZW"[: len(nargs)]) if len(nargs) <= 4 else "V"
        if tp is int:
            return "N"
        if tp is str:
            return "S"
        return "M" if "metre" in self._docs.get(name, "").lower() else "F"

    # ---------------------------------------------------------------- building
    def values(self, ns: argparse.Namespace) -> dict[str, Any]:
        """Field name -> parsed value of the offered fields (those absent from ``ns`` left out)."""
        out: dict[str, Any] = {}
        for name in self.fields:
            key = self._key(name)
            if hasattr(ns, key):
                v = getattr(ns, key)
                out[name] = tuple(v) if isinstance(v, list) else v
        return out

    def build(self, ns: argparse.Namespace) -> T:
        """The dataclass from the parsed options (nested dataclasses first). A value the
        dataclass rejects raises :class:`OptionError` naming its flag."""
        kw: dict[str, Any] = {
            **{name: sub.build(ns) for name, sub in self.nested.items()},
            **self.values(ns),
        }
        try:
            return self.cls(**kw)
        except ValueError as exc:
            raise OptionError(self.message(exc)) from None

    def message(self, exc: ValueError) -> str:
        """The dataclass's message with its field names replaced by flags: ``--flag: ...``."""
        msg = str(exc)
        flag_of = self.flag_of_field()
        head = re.match(r"(\w+)\s*", msg)
        if head is None or head.group(1) not in flag_of:
            return f"invalid {self.title or self.cls.__name__} option: {msg}"
        rest = msg[head.end() :]
        # other fields named in the message (only names with an underscore: a one-word field
        # name such as ``up`` could be an ordinary word of the sentence)
        for name, flag in flag_of.items():
            if "_" in name:
                rest = re.sub(rf"\b{name}\b", flag, rest)
        return f"{flag_of[head.group(1)]}: {rest}"
