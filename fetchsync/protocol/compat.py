"""What the robot's Python 3.6 lacks and the endpoint uses: ``dataclasses`` (3.7).

The standard library's on the laptop (Python >= 3.7, its ``fetchsync`` package has a
``__version__``); on the robot a minimal frozen-dataclass decorator, enough for the
endpoint's small immutable messages: an ``__init__`` taking the fields in order
(defaults, ``default_factory``), ``__repr__``, ``__eq__``, ``__hash__`` when frozen, and
``fields()``. Also on a robot's newer Python: the standard library's module imports
``inspect`` (and with it ``ast``, ``dis``, ``tokenize``...), 16 ms of CPU of the
endpoint's ~55 ms of imports (20 interleaved starts of Python 3.11, 74 -> 58 ms with
the interpreter's own start), paid at every endpoint start, the first push's critical
path, before its hello; the robot builds its operations without ``__init__``
(``Op.from_wire``) and its results are named tuples, so nothing else changes.
"""

import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING or (
    sys.version_info >= (3, 7) and hasattr(sys.modules.get("fetchsync"), "__version__")
):
    from dataclasses import dataclass, field, fields  # novermin
else:  # the robot
    from typing import Any, Optional, Tuple

    _MISSING = object()

    class Field:
        def __init__(self, default: "Any" = _MISSING, default_factory: "Any" = _MISSING) -> None:
            self.name = ""
            self.default = default
            self.default_factory = default_factory

    class FrozenInstanceError(AttributeError):
        pass

    def field(*, default: "Any" = _MISSING, default_factory: "Any" = _MISSING) -> "Any":
        return Field(default, default_factory)

    def fields(cls: "Any") -> "Tuple[Field, ...]":
        return cls.__dataclass_fields__

    def _make(cls: "Any", frozen: bool) -> "Any":
        flds = []
        for name in cls.__dict__.get("__annotations__", {}):
            value = cls.__dict__.get(name, _MISSING)
            f = value if isinstance(value, Field) else Field(default=value)
            f.name = name
            if isinstance(value, Field):
                if f.default is _MISSING:
                    delattr(cls, name)
                else:
                    setattr(cls, name, f.default)
            flds.append(f)
        flds = tuple(flds)
        names = tuple(f.name for f in flds)

        def __init__(self: "Any", *args: "Any", **kwargs: "Any") -> None:
            if len(args) > len(flds):
                raise TypeError("%s takes %d fields" % (cls.__name__, len(flds)))
            for f, v in zip(flds, args):
                if f.name in kwargs:
                    raise TypeError("%s given twice" % f.name)
                object.__setattr__(self, f.name, v)
            for f in flds[len(args) :]:
                if f.name in kwargs:
                    v = kwargs.pop(f.name)
                elif f.default is not _MISSING:
                    v = f.default
                elif f.default_factory is not _MISSING:
                    v = f.default_factory()
                else:
                    raise TypeError("%s lacks field %s" % (cls.__name__, f.name))
                object.__setattr__(self, f.name, v)
            unknown = set(kwargs) - set(names)
            if unknown:
                raise TypeError("%s has no field %s" % (cls.__name__, ", ".join(sorted(unknown))))

        def _values(self: "Any") -> "Tuple[Any, ...]":
            return tuple(getattr(self, n) for n in names)

        def __eq__(self: "Any", other: "Any") -> "Any":
            if other.__class__ is not self.__class__:
                return NotImplemented
            return _values(self) == _values(other)

        def __repr__(self: "Any") -> str:
            return "%s(%s)" % (
                cls.__name__,
                ", ".join("%s=%r" % (n, getattr(self, n)) for n in names),
            )

        def __setattr__(self: "Any", name: str, value: "Any") -> None:
            raise FrozenInstanceError("cannot assign to field %r" % name)

        def __delattr__(self: "Any", name: str) -> None:
            raise FrozenInstanceError("cannot delete field %r" % name)

        cls.__dataclass_fields__ = flds
        cls.__init__ = __init__
        cls.__eq__ = __eq__
        if "__repr__" not in cls.__dict__:
            cls.__repr__ = __repr__
        if frozen:
            cls.__setattr__ = __setattr__
            cls.__delattr__ = __delattr__
            cls.__hash__ = lambda self: hash(_values(self))
        else:
            cls.__hash__ = None
        return cls

    def dataclass(cls: "Optional[Any]" = None, *, frozen: bool = False) -> "Any":
        def wrap(c: "Any") -> "Any":
            return _make(c, frozen)

        return wrap if cls is None else wrap(cls)


__all__ = ["dataclass", "field", "fields"]
