"""One pytree mechanism for every jaxpbr data type (material, lights, camera, geometry, scene, cube map).

A data type is a class deriving from `Pytree` whose fields each declare, once, what they are:

    class Sphere(Pytree):
        center: Any = leaf((0.0, 0.0, 0.0), rank=1)       # array leaf; its last axis is core (xyz)
        radius: Any = leaf(1.0)                           # array leaf, rank 0: a scalar per element
        material: Any = subtree(default_factory=Material)  # a nested pytree (or None, or a tuple)
        # width: int = static(1280)                       # auxiliary data (see below)

        def _validate(self):                              # THE place inputs are converted/checked
            self._set(radius=as_float(self.radius))
            ...

Deriving from `Pytree` turns the class into a frozen dataclass (a generated `__init__` taking the
fields in declaration order, unless the class writes its own) and registers it with JAX. What
each choice is for:

* **Each field declared once, with its nature.** `leaf(rank=r)` is an array child of the pytree;
  `rank` is the number of *trailing core axes* (0 for a scalar, 1 for an RGB colour or an xyz
  point, 3 for an (H, W, C) texture, 4 for a (6, S, S, C) cube level); every axis before them is a
  batch axis that broadcasts with the pixels or is mapped over by `render_batch`. A leaf field may
  also hold None (an absent optional texture) or a tuple of arrays of that rank (the mip levels of
  a `Cubemap`). `subtree()` holds a nested pytree (a `Material`, a tuple of lights, None); its own
  fields declare their ranks. `static()` is auxiliary data: sizes, flags, names. `fields_of(cls)`
  exposes the declarations, so code that needs them (the batch-axis logic of `render_batch`,
  `pack_lights`) reads them instead of keeping its own table of which field is a vector.
* **Static fields are auxiliary data.** They are part of the tree structure (the treedef), which
  `jax.jit` hashes and compares to pick a compiled program: changing an image size or a flag
  compiles a new program, changing a leaf's value does not. They must therefore be hashable
  (ints, floats, bools, strings, tuples of those).
* **Registered with keys** (`register_pytree_with_keys`), so JAX errors and
  `tree_flatten_with_path` name leaves by their path (`.objects[0].material.roughness`).
* **Unflatten bypasses `__init__`.** JAX rebuilds trees with tracers, None (vmap `in_axes`),
  `object()` sentinels, ShapeDtypeStructs or shardings in the leaves; converting or validating those
  would fail or cost time at every trace. (That is also why `jax.tree_util.register_dataclass` is
  not used: its unflatten calls the constructor.)
* **Validation lives in one place per class: `_validate(self)`.** It runs when an object is built
  (`__post_init__`, or at the end of a hand-written `__init__`) and in `replace`, never in
  unflatten or `evolve`. It converts inputs (`_numerics.as_float` keeps Python numbers and tuples
  of them weakly typed, so `base_color=(0.9, 0.6, 0.2)` does not promote a float32 render to
  float64) and checks them. Under `jit`/`vmap`/`grad` the values are tracers: shapes and dtypes are
  still known and are always checked; values (ranges, finiteness, non-zero vectors) are checked
  only when concrete (`_numerics.is_concrete`) -- a tracer's value does not exist yet and is taken
  as given.
* **Immutable.** Assigning a field raises `dataclasses.FrozenInstanceError` (an AttributeError).
  `obj.replace(**changes)` returns a copy validated like the constructor; `evolve(obj, **changes)`
  an *unchecked* copy, and `unchecked(cls, **fields)` an unchecked new object, for library code that
  puts traced or batched values in place inside a transformation (where validation would be
  impossible, or would reject e.g. a leaf that still carries its batch axis).
* **Identity equality** (`eq=False`): `==` on array fields is elementwise and cannot give one bool,
  and a pytree's leaves are not hashable; like arrays, objects compare and hash by identity.
  `dataclasses.replace` keeps working on classes with a generated `__init__`.
* **A readable `__repr__`**: small concrete arrays by value, others as `dtype[shape]` (never a
  whole texture; tracers print too).
* **No `__slots__`**: `dataclass(slots=True)` returns a new class, which cannot be done from
  `__init_subclass__`; the objects are few and small.
"""

from __future__ import annotations

import dataclasses
import re
from typing import Any, Callable, ClassVar, NamedTuple, dataclass_transform

import jax
import numpy as np

from ._numerics import is_concrete

__all__ = ["FieldInfo", "Pytree", "evolve", "fields_of", "leaf", "static", "subtree", "unchecked"]

_SPEC = "jaxpbr.pytree"  # dataclass field metadata key: (kind, rank)
_MISSING: Any = dataclasses.MISSING


class FieldInfo(NamedTuple):
    """How one field of a `Pytree` class is treated."""

    name: str
    #: True: auxiliary data (part of the treedef, hence of the compiled program); False: a child.
    static: bool
    #: Trailing core axes of an array leaf; None for a static field or a subtree.
    rank: int | None

    @property
    def is_array(self) -> bool:
        """An array leaf (`leaf(...)`), as opposed to a static field or a nested pytree."""
        return not self.static and self.rank is not None


def _field(kind: str, rank: int | None, default, default_factory) -> Any:
    return dataclasses.field(default=default, default_factory=default_factory, metadata={_SPEC: (kind, rank)})


def leaf(default: Any = _MISSING, *, rank: int = 0, default_factory: Callable[[], Any] | Any = _MISSING) -> Any:
    """An array leaf with `rank` trailing core axes (0 scalar, 1 vector, 3 an (H, W, C) image...);
    axes before them are batch axes. May hold None, or a tuple of arrays of that rank."""
    if isinstance(rank, bool) or not isinstance(rank, int) or rank < 0:
        raise TypeError(f"leaf rank must be an integer >= 0, got {rank!r}")
    return _field("leaf", rank, default, default_factory)


def subtree(default: Any = _MISSING, *, default_factory: Callable[[], Any] | Any = _MISSING) -> Any:
    """A nested pytree (another `Pytree`, a tuple of them, or None); its fields carry their ranks."""
    return _field("subtree", None, default, default_factory)


def static(default: Any = _MISSING, *, default_factory: Callable[[], Any] | Any = _MISSING) -> Any:
    """Auxiliary data (hashable: sizes, flags, names): part of the treedef and the compiled program."""
    return _field("static", None, default, default_factory)


def _snake(name: str) -> str:
    return re.sub(r"(?<!^)(?=[A-Z])", "_", name).lower()


@dataclass_transform(eq_default=False, frozen_default=True, field_specifiers=(leaf, subtree, static))
class Pytree:
    """Base class of jaxpbr's data types; see the module docstring."""

    __pytree_fields__: ClassVar[tuple[FieldInfo, ...]] = ()

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        dataclasses.dataclass(frozen=True, eq=False, repr=False)(cls)
        # A frozen dataclass installs its own __setattr__/__delattr__ ("cannot assign to field");
        # drop them so Pytree's (which name `replace`) apply. The generated __init__ assigns with
        # object.__setattr__ and is unaffected.
        del cls.__setattr__
        del cls.__delattr__
        infos = []
        for f in dataclasses.fields(cls):
            spec = f.metadata.get(_SPEC)
            if spec is None:
                raise TypeError(
                    f"{cls.__name__}.{f.name}: declare every field of a Pytree with leaf(), subtree() or static()"
                )
            kind, rank = spec
            infos.append(FieldInfo(f.name, kind == "static", rank))
        cls.__pytree_fields__ = tuple(infos)
        _register(cls)

    # -- construction and validation ---------------------------------------------------------
    def __post_init__(self) -> None:
        self._validate()

    def _validate(self) -> None:
        """Convert and check the fields, in place (with `self._set`). The one place a class checks
        its inputs: called on construction and by `replace`, never on unflatten or `evolve`.

        Shapes and dtypes are always checked (they are known under jit); values only when
        `is_concrete` (tracers are taken as given). Classes with a hand-written `__init__` call it
        at the end of `__init__`."""

    def _set(self, **values) -> None:
        """Assign fields during construction / `_validate` (the objects are otherwise immutable)."""
        for name, value in values.items():
            object.__setattr__(self, name, value)

    def replace(self, **changes):
        """A copy with some fields replaced, validated like the constructor."""
        new = evolve(self, **changes)
        new._validate()
        return new

    # -- immutability and display ------------------------------------------------------------
    def __setattr__(self, name, value):
        cls = type(self).__name__
        raise dataclasses.FrozenInstanceError(f"{cls} is immutable; use {_snake(cls)}.replace(field=value).")

    def __delattr__(self, name):
        self.__setattr__(name, None)

    def __repr__(self) -> str:
        parts = (f"{f.name}={_short(getattr(self, f.name, '<unset>'))}" for f in type(self).__pytree_fields__)
        return f"{type(self).__name__}({', '.join(parts)})"


def _register(cls) -> None:
    data = tuple(f.name for f in cls.__pytree_fields__ if not f.static)
    meta = tuple(f.name for f in cls.__pytree_fields__ if f.static)
    keys = tuple(jax.tree_util.GetAttrKey(n) for n in data)

    def flatten(obj):
        d = obj.__dict__
        return tuple(d[n] for n in data), tuple(d[n] for n in meta)

    def flatten_with_keys(obj):
        children, aux = flatten(obj)
        return tuple(zip(keys, children)), aux

    def unflatten(aux, children):
        obj = object.__new__(cls)  # no __init__, no _validate: see the module docstring
        d = obj.__dict__
        d.update(zip(data, children))
        d.update(zip(meta, aux))
        return obj

    jax.tree_util.register_pytree_with_keys(cls, flatten_with_keys, unflatten, flatten)


def fields_of(x) -> tuple[FieldInfo, ...]:
    """The declared fields (name, static, rank) of a `Pytree` class or instance, in order."""
    cls = x if isinstance(x, type) else type(x)
    if not issubclass(cls, Pytree) or cls is Pytree:
        raise TypeError(f"{cls.__name__} is not a jaxpbr pytree type")
    return cls.__pytree_fields__


def _names(cls) -> list[str]:
    return [f.name for f in fields_of(cls)]


def evolve(obj, **changes):
    """A copy of `obj` with some fields replaced, *without* conversion or validation (for traced or
    batched values inside transformations; user code uses `obj.replace`)."""
    names = _names(obj)
    unknown = set(changes) - set(names)
    if unknown:
        raise TypeError(f"{type(obj).__name__} has no field(s) {sorted(unknown)}; fields are {names}.")
    new = object.__new__(type(obj))
    d = new.__dict__
    for n in names:
        d[n] = changes[n] if n in changes else getattr(obj, n)
    return new


def unchecked(cls, **values):
    """A new `cls` holding exactly `values` (every field), *without* conversion or validation."""
    names = _names(cls)
    if set(values) != set(names):
        raise TypeError(
            f"unchecked {cls.__name__} needs exactly the fields {names}; missing "
            f"{sorted(set(names) - set(values))}, unknown {sorted(set(values) - set(names))}."
        )
    obj = object.__new__(cls)
    obj.__dict__.update((n, values[n]) for n in names)
    return obj


def _short(x) -> str:
    """Field display: small concrete arrays by value, other arrays (and tracers) as dtype[shape]."""
    if x is None or isinstance(x, (bool, int, float, str, Pytree)):
        return repr(x)
    if isinstance(x, (tuple, list)):
        inner = ", ".join(_short(e) for e in x)
        return f"[{inner}]" if isinstance(x, list) else f"({inner},)" if len(x) == 1 else f"({inner})"
    shape, dtype = getattr(x, "shape", None), getattr(x, "dtype", None)
    if shape is None or dtype is None:
        return repr(x)
    if isinstance(x, (jax.Array, np.ndarray, np.generic)) and is_concrete(x) and np.size(x) <= 3:
        try:
            return str(np.asarray(x).tolist())
        except (RuntimeError, TypeError, ValueError):  # e.g. a deleted (donated) buffer
            pass
    return f"{dtype}{list(shape)}"
