"""What a LeafSystem may keep without keeping its whole diagram alive.

A diagram built in Python is freed by Python's garbage collector: the diagram, its builder
and its systems refer to one another in cycles that pydrake makes visible to the
collector. A system's Python object must therefore hold no reference the collector cannot
see: one such reference makes the system look used from outside, and with it the diagram
and everything it owns (plant, scene graph, renderers, images: hundreds of MB a station
with a camera) stays for the rest of the process. In pydrake 1.58 these give one:

- a callback of `DeclareAbstractOutputPort` (calculation or allocation) or of a cache
  entry's `ValueProducer` that holds the system, e.g. a bound method `self._calc`: it is
  stored in the system's C++ object (vector output ports and events are fine). Give
  `weak_method(self._calc)` instead.
- a `CacheEntry` kept on the system: it keeps its system alive from pybind11's own
  table. Keep `CacheRef(self, self.DeclareCacheEntry(...))` instead.
- a port, body, frame, model inspector... of ANOTHER system (e.g. the plant's) kept on the
  system or in a callback: each keeps its owner alive the same way. Keep what they give
  (an index, a FrameId, a value) instead, or the owner itself (a plain reference). So do
  the GeometryIds in the list `plant.GetCollisionGeometriesForBody(body)` returns:
  references into the plant. Keep `id_values(ids)` instead.

tests/test_memory.py checks that every kind of station is freed when dropped.
"""

from __future__ import annotations

import types
import weakref


def weak_method(method: types.MethodType):
    """A function calling the bound `method` with its arguments, holding the method's
    object only weakly. The Python side of a system added to a diagram lives as long as its
    C++ object, which alone calls the callback: the system is there whenever it is called.
    TypeError for anything but a bound method (a plain function or lambda holds no system
    unless it closes over one: write it so that it does not)."""
    if not isinstance(method, types.MethodType):
        raise TypeError(f"weak_method needs a bound method, got {type(method).__name__}")
    ref = weakref.WeakMethod(method)
    name = method.__func__.__qualname__

    def call(*args):
        bound = ref()
        if bound is None:  # only if Drake called a system's callback after freeing it
            raise ReferenceError(f"{name}: its system no longer exists")
        return bound(*args)

    call.__name__ = method.__func__.__name__
    call.__qualname__ = f"weak_method({name})"
    return call


class CacheRef:
    """A system's cache entry, kept by its index: `Eval(context)` and `ticket()` as the
    `CacheEntry` that `DeclareCacheEntry` returned (looked up at each Eval, a fraction of a
    microsecond). Holds the system by a plain reference, a cycle the collector sees."""

    __slots__ = ("_system", "_index", "_ticket")

    def __init__(self, system, entry):
        self._system = system
        self._index = entry.cache_index()
        self._ticket = entry.ticket()

    def Eval(self, context):
        return self._system.get_cache_entry(self._index).Eval(context)

    def ticket(self):
        return self._ticket


def id_values(ids) -> frozenset[int]:
    """The values of Drake identifiers (GeometryId...), as a set to look ids up in by
    `id.get_value()`: what a system keeps of ids that a plant returns by reference. Values
    given as ints pass as they are."""
    return frozenset(i if isinstance(i, int) else int(i.get_value()) for i in ids)
