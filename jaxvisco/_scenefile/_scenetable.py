"""Typed access to one table of a scene file, with one-line messages that name the file,
the table, the key, the bad value and what is accepted (`_scenefile`)."""

import math

import numpy as np

_REQUIRED = object()


class Table:
    """One TOML table being read: typed access with messages naming file, table, key."""

    def __init__(self, name, data, where, accepted, aliases=None):
        """`accepted`: the keys of the table; `aliases`: deprecated names of some of them
        (old name -> the accepted key or the place that replaces it), accepted too but
        not listed in messages (`deprecated` names those used)."""
        self.name, self.where, self.data = name, where, data
        if not isinstance(data, dict):
            raise ValueError(f"{name}: {where}: expected a table, got {data!r}.")
        aliases = aliases or {}
        for key in data:
            if key not in accepted and key not in aliases:
                raise ValueError(f"{name}: {where}: unknown key {key!r}; accepted: {', '.join(accepted)}.")
        self.deprecated = [f"{name}: {where}: {key} is deprecated, write {aliases[key]}"
                           for key in data if key in aliases]

    def error(self, key, msg):
        return ValueError(f"{self.name}: {self.where}: {key}: {msg}")

    def has(self, key):
        return key in self.data

    def raw(self, key, default=_REQUIRED):
        if key not in self.data:
            if default is _REQUIRED:
                raise self.error(key, "missing (required).")
            return default
        return self.data[key]

    def number(self, key, default=_REQUIRED, positive=False, allow_inf=False, minimum=None):
        v = self.raw(key, default)
        if v is default and key not in self.data:
            return v
        if isinstance(v, str) and allow_inf and v.strip().lower() == "inf":
            v = math.inf
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.error(key, f"expected a number, got {v!r}.")
        v = float(v)
        accepted = "a number > 0" if positive else "a finite number" if minimum is None else f"a number >= {minimum:g}"
        if allow_inf:
            accepted += " or inf"
        if math.isnan(v) or (math.isinf(v) and not (allow_inf and v > 0)) or (positive and not v > 0) or \
                (minimum is not None and v < minimum):
            raise self.error(key, f"got {v!r}; accepted: {accepted}.")
        return v

    def integer(self, key, default=_REQUIRED, minimum=None, maximum=None):
        v = self.raw(key, default)
        if v is default and key not in self.data:
            return v
        if isinstance(v, bool) or not isinstance(v, int) or (minimum is not None and v < minimum) or \
                (maximum is not None and v > maximum):
            rng = f"an integer >= {minimum}" if maximum is None else f"an integer in [{minimum}, {maximum}]"
            raise self.error(key, f"got {v!r}; accepted: {rng}.")
        return v

    def string(self, key, default=_REQUIRED, choices=None):
        v = self.raw(key, default)
        if v is default and key not in self.data:
            return v
        if not isinstance(v, str) or (choices is not None and v not in choices):
            accepted = "a string" if choices is None else ", ".join(repr(c) for c in choices)
            raise self.error(key, f"got {v!r}; accepted: {accepted}.")
        return v

    def boolean(self, key, default=_REQUIRED):
        v = self.raw(key, default)
        if not isinstance(v, bool):
            raise self.error(key, f"got {v!r}; accepted: true or false.")
        return v

    def vector(self, key, n, default=_REQUIRED, what="numbers"):
        v = self.raw(key, default)
        if v is default and key not in self.data:
            return v
        ok = isinstance(v, list) and len(v) == n and all(isinstance(a, (int, float)) and not isinstance(a, bool)
                                                          and math.isfinite(a) for a in v)
        if not ok:
            raise self.error(key, f"got {v!r}; accepted: a list of {n} finite {what}.")
        return np.asarray(v, dtype=np.float64)

    def names(self, key):
        v = self.raw(key)
        if isinstance(v, str):
            v = [v]
        if not (isinstance(v, list) and v and all(isinstance(a, str) for a in v)):
            raise self.error(key, f"got {v!r}; accepted: a group name or a list of group names.")
        return v
