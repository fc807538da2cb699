"""Validated reading of TOML tables: every value checked, every error names its key path.

Internal to the rig loader (and reused by other TOML readers such as task and daemon configs).
A ``Table`` wraps one TOML table; each getter consumes a key, checks type, finiteness and range,
and raises :class:`~rt_runtime.errors.RigProfileError` (a ``ConfigurationError``) naming the key
path and what is allowed. ``finish()`` rejects keys nobody asked for, so typos never pass silently.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, TypeVar

from rt_runtime.errors import ConfigurationError, RigProfileError

_T = TypeVar("_T")
_MISSING: Any = object()


def _fmt(x: float) -> str:
    return f"{x:g}"


class Table:
    """A TOML table being read and validated.

    Args:
        data: The parsed table.
        path: Dotted key path of this table ("" for the document root).
        source: File name or profile name, used in error messages.
        error_type: Exception class raised on invalid input.
    """

    def __init__(
        self,
        data: Mapping[str, Any],
        path: str = "",
        source: str = "",
        error_type: type[ConfigurationError] = RigProfileError,
    ) -> None:
        self._data = data
        self._path = path
        self._source = source
        self._error_type = error_type
        self._used: set[str] = set()
        self._asked: set[str] = set()

    @property
    def path(self) -> str:
        """Dotted key path of this table."""
        return self._path

    @property
    def source(self) -> str:
        """File or profile name the table came from."""
        return self._source

    def key_path(self, key: str) -> str:
        """Dotted path of ``key`` inside this table."""
        return f"{self._path}.{key}" if self._path else key

    def error(self, key: str, message: str) -> ConfigurationError:
        """An error of this table's type naming ``key``'s path."""
        if self._error_type is RigProfileError:
            return RigProfileError(self.key_path(key), message, self._source)
        where = f"{self._source}: " if self._source else ""
        return self._error_type(f"{where}{self.key_path(key)}: {message}")

    def has(self, key: str) -> bool:
        """Whether ``key`` is present."""
        return key in self._data

    def keys(self) -> list[str]:
        """The keys present in this table, in file order."""
        return list(self._data.keys())

    def _get(self, key: str, default: Any) -> Any:
        self._asked.add(key)
        if key not in self._data:
            if default is _MISSING:
                raise self.error(key, "missing (required)")
            return default
        self._used.add(key)
        return self._data[key]

    def number(
        self,
        key: str,
        *,
        gt: float | None = None,
        ge: float | None = None,
        lt: float | None = None,
        le: float | None = None,
        default: Any = _MISSING,
    ) -> float:
        """A finite real number within the given bounds."""
        value = self._get(key, default)
        return self._check_number(key, value, gt=gt, ge=ge, lt=lt, le=le)

    def _check_number(
        self,
        key: str,
        value: Any,
        *,
        gt: float | None = None,
        ge: float | None = None,
        lt: float | None = None,
        le: float | None = None,
    ) -> float:
        allowed = _allowed(gt, ge, lt, le)
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.error(key, f"must be a number{allowed} (got {value!r})")
        try:
            x = float(value)
        except OverflowError:  # an integer beyond the float range
            x = math.inf
        if not math.isfinite(x):
            raise self.error(key, f"must be a finite number{allowed} (got {value!r})")
        if (
            (gt is not None and not x > gt)
            or (ge is not None and not x >= ge)
            or (lt is not None and not x < lt)
            or (le is not None and not x <= le)
        ):
            raise self.error(key, f"must be{allowed} (got {_fmt(x)})")
        return x

    def integer(
        self, key: str, *, ge: int | None = None, le: int | None = None, default: Any = _MISSING
    ) -> int:
        """An integer within the given bounds."""
        value = self._get(key, default)
        allowed = _allowed(None, ge, None, le)
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(key, f"must be an integer{allowed} (got {value!r})")
        if (ge is not None and value < ge) or (le is not None and value > le):
            raise self.error(key, f"must be{allowed} (got {value})")
        return int(value)

    def boolean(self, key: str, *, default: Any = _MISSING) -> bool:
        """A boolean (``true`` or ``false``)."""
        value = self._get(key, default)
        if not isinstance(value, bool):
            raise self.error(key, f"must be true or false (got {value!r})")
        return value

    def string(
        self, key: str, *, choices: tuple[str, ...] | None = None, default: Any = _MISSING
    ) -> str:
        """A string, optionally one of ``choices``."""
        value = self._get(key, default)
        if not isinstance(value, str):
            raise self.error(key, f"must be a string (got {value!r})")
        if choices is not None and value not in choices:
            raise self.error(key, f"must be one of {', '.join(choices)} (got {value!r})")
        return value

    def strings(self, key: str, default: Any = _MISSING) -> tuple[str, ...]:
        """A list of strings."""
        value = self._get(key, default)
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise self.error(key, f"must be a list of strings (got {value!r})")
        return tuple(value)

    def numbers(
        self,
        key: str,
        length: int | None = None,
        *,
        ge: float | None = None,
        le: float | None = None,
        default: Any = _MISSING,
    ) -> tuple[float, ...]:
        """A list of finite numbers, optionally of a fixed length and within bounds."""
        value = self._get(key, default)
        if not isinstance(value, list):
            raise self.error(key, f"must be a list of numbers (got {value!r})")
        if length is not None and len(value) != length:
            raise self.error(key, f"must have exactly {length} numbers (got {len(value)})")
        return tuple(
            self._check_number(f"{key}[{i}]", v, ge=ge, le=le) for i, v in enumerate(value)
        )

    def range(
        self,
        key: str,
        *,
        ge: float | None = None,
        le: float | None = None,
        default: Any = _MISSING,
    ) -> tuple[float, float]:
        """A ``[min, max]`` pair with ``min < max`` inside the given bounds."""
        lo, hi = self.numbers(key, 2, ge=ge, le=le, default=default)
        if not lo < hi:
            raise self.error(key, f"min must be < max (got [{_fmt(lo)}, {_fmt(hi)}])")
        return lo, hi

    def ordered(self, lo_key: str, lo: float, hi_key: str, hi: float) -> None:
        """Check that ``lo < hi`` for two keys of this table."""
        if not lo < hi:
            raise self.error(
                lo_key, f"must be < {self.key_path(hi_key)} (got {_fmt(lo)} >= {_fmt(hi)})"
            )

    def table(self, key: str) -> Table:
        """A required sub-table."""
        value = self._get(key, _MISSING)
        if not isinstance(value, Mapping):
            raise self.error(key, f"must be a table (got {type(value).__name__})")
        return Table(value, self.key_path(key), self._source, self._error_type)

    def optional_table(self, key: str) -> Table | None:
        """A sub-table, or None when absent."""
        self._asked.add(key)
        if key not in self._data:
            return None
        return self.table(key)

    def raw(self, key: str, default: Any = _MISSING) -> Any:
        """The raw value of ``key`` (the caller validates it)."""
        return self._get(key, default)

    def finish(self) -> None:
        """Reject keys that no getter consumed."""
        unknown = [k for k in self._data if k not in self._used]
        if unknown:
            known = sorted(self._asked)
            raise self.error(
                unknown[0],
                f"unknown key; allowed here: {', '.join(known) if known else '(none)'}",
            )


def _allowed(gt: float | None, ge: float | None, lt: float | None, le: float | None) -> str:
    lo = f"> {_fmt(gt)}" if gt is not None else (f">= {_fmt(ge)}" if ge is not None else "")
    hi = f"< {_fmt(lt)}" if lt is not None else (f"<= {_fmt(le)}" if le is not None else "")
    if lo and hi:
        return f" {lo} and {hi}"
    if lo or hi:
        return f" {lo or hi}"
    return ""
