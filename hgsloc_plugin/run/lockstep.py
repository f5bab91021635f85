"""Lockstep batches: many queries refined together, their renders in shared launches.

Each query of a batch runs in a worker thread whose refiner renders through a :class:`DeviceProxy`: every
device call is handed to the thread that runs the batch, and the worker waits for its answer. When every live
query waits, that thread serves one round: the calls that cannot be batched (query uploads and the like) if any
wait, else the largest group of ``window_cost`` or ``pose_gradient`` calls of one map, image size and settings,
in one launch (each pose scored against its own query, whose statistics sit in a slot of one device array per
image size, copied there once: ``Renderer.stack_window_queries``; and rendered with its own query's camera:
intrinsics may differ); the queries served resume, the others wait for a later round, so queries that fell out
of step meet again at a common call.
So:

- the host talks to the device once per step of the batch, not once per render call of each query;
- Taichi is only ever called from one thread (CUDA contexts are per thread), one call at a time;
- a pose's numbers do not depend on the other poses of its launch, so every query's poses equal those of one
  query at a time, whatever the batch size or the order in which queries finish.

A query that finishes leaves the batch and the next one takes its place; at most ``batch_size`` are live.
On maps of ``Tuning.working_set_min`` Gaussians or more each query renders from its own working set (a
subset of the map); the calls of one group then render from the union of their subsets
(``Renderer.union``: every pose's image is the whole map's, bit for bit) when it holds at most
``union_limit`` times the largest subset's Gaussians (``backend.DEFAULT_UNION_LIMIT``: none on the CPU, any on
CUDA), else the calls of the group's most common subset go together and the others wait.
"""

from __future__ import annotations

import copy
import inspect
import logging
import threading
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np
import taichi as ti

from ..core.backend import default_union_limit
from ..core.camera import Camera
from ..render.protocol import BatchingRenderer, RendererLike

logger = logging.getLogger(__name__)

#: unions of working sets a :class:`Lockstep` keeps for the next rounds (each a copy of its Gaussians on the device)
UNIONS_KEPT = 4
#: query slots per image size a :class:`Lockstep` keeps on the device, per query of its batch
SLOTS_PER_QUERY = 2
#: the batched calls, and how each one's keyword values are read from its arguments
_BATCHED = {name: inspect.signature(getattr(BatchingRenderer, name)) for name in ("window_cost", "pose_gradient")}


class BatchCancelled(BaseException):
    """Raised in a query's worker when its batch stops early (an error in the caller, an interrupt); like
    ``KeyboardInterrupt`` it is not an ``Exception``, so the query ends without being recorded as failed."""


@dataclass(eq=False)
class _Slot:
    """One live query: its job, the device call it waits on, the call's answer and, at the end, its result."""

    job: Callable[..., object]
    request: tuple | None = None  # (target, method name, args, kwargs)
    key: object = None  # what the request must share with others to go into one launch (None: alone)
    arguments: dict | None = None  # a batchable request's arguments by name, defaults applied
    reply: tuple | None = None  # (ok, value or exception)
    finished: bool = False
    result: object = None
    resume: threading.Event = field(default_factory=threading.Event)


class Lockstep:
    """Runs jobs (one query each) in lockstep on one device; see the module docstring.

    Args:
        batch_size: live queries at most (the memory bound: a launch holds up to this many queries' poses).
        union_limit: how much larger than the largest working set of a group the union its launch renders from
            may be (None: the backend's, ``backend.default_union_limit``; 1: only calls on one working set share a
            launch; ``math.inf``: any union, up to the whole map).
    """

    def __init__(self, batch_size: int, union_limit: float | None = None):
        if int(batch_size) != batch_size or batch_size < 1:
            raise ValueError(f"batch_size must be a positive integer, got {batch_size!r}")
        union_limit = default_union_limit() if union_limit is None else float(union_limit)
        if not union_limit >= 1.0:
            raise ValueError(f"union_limit must be >= 1, got {union_limit!r}")
        self.batch_size = int(batch_size)
        self.union_limit = union_limit
        self._unions: dict[tuple, tuple[list, BatchingRenderer]] = {}
        self._cond = threading.Condition()
        self._cancelled = False
        self._slots: dict[tuple, QuerySlots] = {}  # per image size
        self.launches = 0  # device calls served (a batched launch counts once)
        self.requests = 0  # device calls the queries made
        self.union_launches = 0  # launches rendered from the union of several working sets

    def run(self, jobs: Iterable[tuple[object, Callable[[DeviceProxy], object]]]) -> Iterator[tuple[object, object]]:
        """(key, result) of each job as it finishes; a job is ``(key, fn)`` and ``fn(proxy_factory)`` runs in a
        worker thread, where ``proxy_factory(renderer)`` gives that job's :class:`DeviceProxy` of a renderer."""
        pending = iter(jobs)
        self._cancelled = False  # a gate runs batch after batch (its counts add up)
        live: list[tuple[object, _Slot]] = []
        exhausted = False
        try:
            while True:
                while not exhausted and len(live) < self.batch_size:
                    nxt = next(pending, None)
                    if nxt is None:
                        exhausted = True
                        break
                    live.append((nxt[0], self._start(nxt[1])))
                if not live:
                    return
                self._wait_all([s for _, s in live])
                for key, s in live:
                    if s.finished:
                        if isinstance(s.result, BaseException):
                            raise s.result
                        yield key, s.result
                live = [(k, s) for k, s in live if not s.finished]
                self._serve([s for _, s in live])
        finally:
            self._cancel([s for _, s in live])

    def _wait_all(self, slots: list[_Slot]) -> None:
        """Until every live query waits on a device call or has finished."""
        with self._cond:
            self._cond.wait_for(lambda: all(s.finished or s.request is not None for s in slots))

    # ---- workers ----

    def _start(self, fn: Callable) -> _Slot:
        slot = _Slot(fn)

        def work():
            try:
                slot.result = fn(lambda renderer: DeviceProxy(self, slot, renderer))
            except BaseException as exc:  # noqa: BLE001 - handed to the batch's thread, raised there
                slot.result = exc
            finally:
                with self._cond:
                    slot.finished = True
                    self._cond.notify_all()

        threading.Thread(target=work, name="hgsloc-lockstep", daemon=True).start()
        return slot

    def call(self, slot: _Slot, target, name: str, args: tuple, kwargs: dict):
        """Run ``target.name(*args, **kwargs)`` on the batch's thread (from a worker); returns its value."""
        with self._cond:
            if self._cancelled:
                raise BatchCancelled("the batch was stopped")
            slot.request = (target, name, args, kwargs)
            slot.key, slot.arguments = _batch_key(target, name, args, kwargs)
            self._cond.notify_all()
        slot.resume.wait()
        slot.resume.clear()
        ok, value = slot.reply
        slot.reply = None
        if not ok:
            raise value
        return value

    def _cancel(self, slots: list[_Slot]) -> None:
        """Answer every waiting worker with :class:`BatchCancelled` so that its thread ends."""
        with self._cond:
            self._cancelled = True
            for s in slots:
                if s.request is not None and not s.finished:
                    s.request, s.reply = None, (False, BatchCancelled("the batch was stopped"))
                    s.resume.set()

    # ---- the device thread ----

    def _serve(self, slots: list[_Slot]) -> None:
        """Serve one round: every waiting call that cannot be batched (uploads and the like: cheap, and each
        moves its query on to its next render) when there are any, else the largest group of batchable calls
        (the first met on a tie); then wake the queries served. The others keep waiting, so queries that fell
        out of step (different routes, iteration counts) meet again at a common call instead of each taking
        a launch of its own."""
        if not slots:
            return
        groups: dict[object, list[_Slot]] = {}
        singles = []
        for s in slots:
            if s.key is None:
                singles.append(s)
            else:
                groups.setdefault(s.key, []).append(s)
        if singles:
            for s in singles:
                s.reply = _invoke(*s.request)
            served = singles
        else:
            served, target = self._together(max(groups.values(), key=len))  # max: the first of equal lengths
            if len(served) > 1:
                self._launch(served, target)
            else:
                served[0].reply = _invoke(*served[0].request)
        self.requests += len(served)
        self.launches += len(singles) or 1
        for s in served:
            s.request = s.key = s.arguments = None
            s.resume.set()

    def _together(self, group: list[_Slot]) -> tuple[list[_Slot], BatchingRenderer]:
        """The calls of ``group`` (one map, method, image size and settings) that go into one launch, and the renderer
        it renders from: all of them and their renderers' union when that is within ``union_limit``, else those
        of the most common renderer (the first met on a tie) and that renderer."""
        targets = {id(s.request[0]): s.request[0] for s in group}
        union = next(iter(targets.values())) if len(targets) == 1 else self._union(list(targets.values()))
        if union is not None:
            return group, union
        count = Counter(id(s.request[0]) for s in group)
        best = max(count, key=count.get)  # max keeps the first of equal counts
        return [s for s in group if id(s.request[0]) == best], targets[best]

    def _union(self, targets: list[BatchingRenderer]) -> BatchingRenderer | None:
        """The renderer of the union of ``targets``' Gaussians (``Renderer.union``), or None when it holds
        more than ``union_limit`` times the largest's (the last ``UNIONS_KEPT`` are kept: the groups of a batch
        repeat until a query selects a new working set, and each union holds a copy of its Gaussians)."""
        def make() -> BatchingRenderer | None:
            if not self.union_limit > 1.0 or len({id(t.root) for t in targets}) > 1:
                return None  # renderers of different maps (level-of-detail cuts) have no union
            union = targets[0].root.union(targets)
            return union if union.n <= self.union_limit * max(t.n for t in targets) else None

        return _kept_by_identity(self._unions, sorted(targets, key=id), UNIONS_KEPT, make)

    def _launch(self, group: list[_Slot], target: BatchingRenderer) -> None:
        """One launch for the calls of ``group`` (same map, method, image size and settings) on ``target`` (their
        renderer or their renderers' union: :meth:`_together`), each pose with its call's camera."""
        _, name, _, _ = group[0].request
        calls = [s.arguments for s in group]
        stats = list({id(c["qstats"]): c["qstats"] for c in calls}.values())
        shape = tuple(stats[0].shape[1:])
        slots = self._slots.get(shape)
        if slots is None:  # one per image size, made once
            slots = self._slots[shape] = QuerySlots(SLOTS_PER_QUERY * self.batch_size, shape)
        poses = [p for c in calls for p in c["poses"]]
        args = {k: v for k, v in calls[0].items() if k not in ("self", "poses", "qstats", "query_index")}
        if any(c["camera"] != args["camera"] for c in calls):  # queries of other intrinsics: a camera per pose
            args["camera"] = [c["camera"] for c in calls for _ in c["poses"]]
        self.union_launches += len({id(s.request[0]) for s in group}) > 1
        try:
            stacked, slot_of = slots.place(target, stats)
            index = np.concatenate([np.full(len(c["poses"]), slot_of[id(c["qstats"])], np.int32) for c in calls])
            out = getattr(target, name)(poses=poses, qstats=stacked, query_index=index, **args)
        except Exception:  # noqa: BLE001 - each call then gets its own answer (and its own error)
            for s in group:
                s.reply = _invoke(*s.request)
            return
        ends = np.cumsum([len(c["poses"]) for c in calls])[:-1]
        parts = (zip(*(np.split(a, ends) for a in out)) if isinstance(out, tuple)
                 else np.split(out, ends))
        for s, part in zip(group, parts):
            s.reply = (True, part)


class QuerySlots:
    """One image size's query statistics in the slots of one device array (``capacity`` of them, made on first
    use): each query's are copied in once and keep their slot while they are used, the least recently used
    giving way to new ones, so a launch over any group of live queries needs no new array and no copy of those
    already in place."""

    def __init__(self, capacity: int, shape: tuple[int, ...]):
        self.capacity = capacity
        self.shape = shape  # one query's statistics: (H, W, 3, NQ)
        self.array = None
        self.held: dict[int, tuple[object, int]] = {}  # id(statistics) -> (statistics, slot), least recent first

    def place(self, target: BatchingRenderer, stats: list) -> tuple[object, dict[int, int]]:
        """(the device array [capacity, H, W, 3, NQ], {id(statistics): slot}) with every one of ``stats`` (at most
        ``capacity``, of this size) in its slot."""
        if self.array is None:
            self.array = ti.ndarray(ti.f32, (self.capacity,) + self.shape)
        wanted = {id(q) for q in stats}
        slot_of = {}
        for q in stats:
            held = self.held.pop(id(q), None)  # held entries keep their statistics alive: an id is never reused
            if held is None:
                used = {k for _, k in self.held.values()}
                free = next((k for k in range(self.capacity) if k not in used), None)
                if free is None:  # the least recently used of the others gives way
                    free = self.held.pop(next(i for i in self.held if i not in wanted))[1]
                target.stack_window_queries([q], out=self.array, slots=[free])
                held = (q, free)
            self.held[id(q)] = held  # most recent last
            slot_of[id(q)] = held[1]
        return self.array, slot_of


def _kept_by_identity(cache: dict, objects: list, size: int, make: Callable[[], object]):
    """``make()``'s value for ``objects`` (these very objects, in this order), from ``cache`` when it holds it;
    a new value is kept there, the cache emptied first when it holds ``size``. The cache keeps references to the
    objects, so their ids stay unique while their entry lives."""
    key = tuple(id(o) for o in objects)
    hit = cache.get(key)
    if hit is not None and all(a is b for a, b in zip(hit[0], objects)):
        return hit[1]
    if len(cache) >= size:
        cache.clear()
    value = make()
    cache[key] = (list(objects), value)
    return value


def _batch_key(target, name: str, args: tuple, kwargs: dict) -> tuple[object, dict | None]:
    """(what the call must share with others to go into one launch, its arguments by name with defaults
    applied), or (None, None) when it goes alone; worked out once, when the call is made."""
    if name not in _BATCHED:
        return None, None
    if not _batches(target):
        return None, None
    try:
        bound = _BATCHED[name].bind(None, *args, **kwargs)
    except TypeError:
        return None, None
    bound.apply_defaults()
    a = bound.arguments
    if a["query_index"] is not None or a["qstats"].shape[0] != 1:
        return None, None
    camera = a["camera"]
    if not isinstance(camera, Camera):
        return None, None
    return (id(target.root), name, (camera.width, camera.height), tuple(float(v) for v in np.ravel(a["background"])),
            float(a["mask_alpha"]), bool(a.get("luminance", False))), a


_BATCHES: dict[type, bool] = {}  # renderer type -> whether it is a BatchingRenderer (checked once per type)


def _batches(target) -> bool:
    """Whether ``target`` is a :class:`BatchingRenderer`; a type that is not is named once in the log (its calls
    run alone)."""
    kind = type(target)
    known = _BATCHES.get(kind)
    if known is None:
        known = _BATCHES[kind] = isinstance(target, BatchingRenderer)
        if not known:
            logger.info("lockstep: %s is no BatchingRenderer (root, union, stack_window_queries): each query's "
                        "calls run alone, the same poses without shared launches", kind.__name__)
    return known


def _invoke(target, name: str, args: tuple, kwargs: dict) -> tuple:
    try:
        return True, getattr(target, name)(*args, **kwargs)
    except Exception as exc:  # noqa: BLE001 - raised again in the worker
        return False, exc


def refine_queries(refiner, queries: Iterable, batch_size: int = 1, gate: Lockstep | None = None):
    """(query, result) pairs of ``batch.Query`` objects as they finish, in this process: one at a time
    (``batch_size`` 1) or ``batch_size`` queries in lockstep (:class:`Lockstep`: the same poses; ``gate``: a
    ready one, whose counts of device calls the caller reads)."""
    if batch_size <= 1 and gate is None:
        for q in queries:
            yield q, q.refine_with(refiner)
        return

    def job(q):
        def fn(proxy):
            mine = copy.copy(refiner)  # the same settings, rendering through this query's proxy
            mine.renderer = proxy(refiner.renderer)
            return q.refine_with(mine)

        return q, fn

    yield from (gate or Lockstep(batch_size)).run(job(q) for q in queries)


class DeviceProxy:
    """A renderer seen from a lockstep worker: its methods run on the batch's thread (their renderers come back
    as proxies too); plain attributes (``n``, ``config``, ``source_index``) are read directly."""

    def __init__(self, gate: Lockstep, slot: _Slot, target):
        self._gate, self._slot, self._target = gate, slot, target

    def __getattr__(self, name: str):
        value = getattr(self._target, name)
        if not callable(value):
            return value

        def call(*args, **kwargs):
            out = self._gate.call(self._slot, self._target, name, args, kwargs)
            return DeviceProxy(self._gate, self._slot, out) if isinstance(out, RendererLike) else out

        return call
