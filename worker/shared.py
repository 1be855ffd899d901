"""A shared team (protocol 8): workers on one machine split each generation in shared memory.

A zenoh team (`worker.team`) pays every generation a message round trip through the router, a
fixed slice per member however their speeds vary, and a copy of the GA on every member: more
than a generation of a few milliseconds gains from a second core. Members on their leader's
machine need none of it. The leader maps a small file in /dev/shm and, each generation,
writes the genomes it asked there; the members (and the leader) claim chunks of them one
after the other and write each chunk's fitness and components into their own region of the
file. The leader alone waits for the last chunks, tells and asks. Waiting costs no CPU (a
byte on a Unix datagram socket wakes the waiter), so the server gets the cores the team does
not use, and the members end a generation within one chunk of each other whatever their
speeds.

What keeps a run bit-identical to `evolve`:
- a member evaluates the genomes the leader asked, for the generation the leader names;
- each chunk it writes carries that generation's stamp before and after its data (a seqlock),
  so the leader never reads a chunk written for another generation, nor one being rewritten;
- each member writes only its own region, so a stalled member's late write lands nowhere the
  leader reads;
- a chunk claimed but not written in time (`PATIENCE`: its member is descheduled, hangs or
  died) is evaluated by the leader too, whichever copy it reads first.
Only the leader holds the lease and sends results, as in a zenoh team. Reading stores in the
order they were made needs total store order (x86-64), and the wake-up sockets Linux's
abstract namespace, so elsewhere the same team splits its generations over zenoh.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import mmap
import os
import platform
import socket
import sys
import threading
import time
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np

from schemas.wire import Job, team_cuts
from worker.team import MEMBER_WAIT_S, Evaluator, checked_evaluation

log = logging.getLogger(__name__)

RING = 2
"""Generations whose genomes and chunks the file holds: the one being evaluated, and the one
before for a member that finishes a chunk of it late (its write is then ignored)."""
CHUNKS_PER_MEMBER = 2
"""A generation is cut into this many chunks per member: fewer leave the leader waiting
longer on the last one; more cost each its call of the evaluator (about 0.03 ms) and a
narrower batch (25 individuals evaluate 7 % slower per individual than 100, 13 of them 15 %).
At the paper's scale 2 took the workers 0.17-0.27 s less CPU a run than 4 (docs/protocol.md)."""
PATIENCE = 2.0
"""The leader evaluates a member's chunk itself once no chunk has come for this many times
its own last chunk's time: the member is descheduled (by the server's recording on a shared
core), hangs or died. Both copies are the same; the first one read counts."""

JOIN_GRACE_S = 1.0
"""Beyond MEMBER_WAIT_S, how long after the span went out a member may still map the file
(its place came within the server's 0.25 s invitation)."""
STOP_POLL_S = 0.1
"""A waiting member looks at its stop request at least this often."""

_MAGIC = 0x45564331_53484D32  # "EVC1SHM2"
_HEADER = 4
"""int64 words: magic, layout fingerprint, stamp of the generation to evaluate, over flag."""
_MAGIC_AT, _SHAPE_AT, _PUBLISHED_AT, _OVER_AT = range(_HEADER)


def supported() -> bool:
    """Shared teams need total store order (x86-64) and Linux (/dev/shm, abstract sockets)."""
    return sys.platform == "linux" and platform.machine().lower() in ("x86_64", "amd64")


@functools.cache
def machine() -> str:
    """What this process shares memory with: the host name, the kernel's boot id and the
    inodes of its IPC and network namespaces (a container with the host's name but its own
    /dev/shm differs); empty where shared teams are not `supported`."""
    if not supported():
        return ""
    try:
        boot = Path("/proc/sys/kernel/random/boot_id").read_text().strip()
        spaces = [os.stat(f"/proc/self/ns/{ns}").st_ino for ns in ("ipc", "net")]
    except OSError:
        return ""
    return f"{socket.gethostname()}/{boot}/{spaces[0]}/{spaces[1]}"[:255]


SHM = Path("/dev/shm")
_PREFIX = "evocolony-team-"
"""Of every team's file (after it, the team id) and wake-up socket (the team id, a member)."""
STALE_AFTER_S = 60.0
"""A team file this old whose leader is gone is left over (a live leader removes the name
within MEMBER_WAIT_S + JOIN_GRACE_S of its span's start, or at its first generation after)."""


def segment_path(team_id: str) -> Path:
    """The team's file, in memory only."""
    return SHM / f"{_PREFIX}{team_id}"


def sweep(directory: Path = SHM) -> list[Path]:
    """Remove the team files (drafts too) that leaders killed in their span's first seconds
    left behind (a member invited but never joined kept the name): older than STALE_AFTER_S,
    with no process in this network namespace bound to the leader's wake-up socket (from
    another namespace a live leader looks gone, but its name is gone by then anyway, and
    mappings outlive names). Returns what it removed.

    A worker sweeps when it starts, so a host's /dev/shm does not fill up over months."""
    removed: list[Path] = []
    for path in directory.glob(f"{_PREFIX}*"):
        team_id = path.name[len(_PREFIX) :].removesuffix(".draft")
        try:
            age = time.time() - path.stat().st_mtime
        except FileNotFoundError:
            continue
        if age < STALE_AFTER_S or _bound(_address(team_id, 0)):
            continue
        try:
            path.unlink()
        except FileNotFoundError:
            continue
        except OSError as exc:  # another user's file (/dev/shm is sticky): theirs to sweep
            log.debug("cannot remove %s: %s", path, exc)
            continue
        removed.append(path)
        log.info("removed %s: its leader is gone", path)
    return removed


def _bound(address: str) -> bool:
    """Whether a process holds the datagram socket `address` (connecting sends nothing)."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as probe:
        try:
            probe.connect(address)
        except (ConnectionRefusedError, FileNotFoundError):
            return False
    return True


def chunk_count(population: int, members: int) -> int:
    """Chunks a generation is cut into for `members` (at most one per individual)."""
    return min(population, CHUNKS_PER_MEMBER * members)


def stamp(generation: int, digest: str) -> int:
    """A generation's stamp: the generation (+1, so that 0 is never one) and its genome
    digest. Each span has its own file, so a stamp only tells its generations apart."""
    return ((generation + 1) << 32) | int(digest, 16)


def _address(team_id: str, member: int) -> str:
    """A member's wake-up socket, in the abstract namespace (gone with its process)."""
    return f"\0{_PREFIX}{team_id}-{member}"


class _Segment:
    """The mapped file and its arrays (views that must go before the map closes)."""

    def __init__(self, path: Path, job: Job, create: bool) -> None:
        config, members = job.config, len(job.team)
        p, t, w = config.population, config.trials, config.network_spec.weight_count
        self.chunks = chunk_count(p, members)
        helpers = members - 1
        words = _HEADER + members + RING * self.chunks * (1 + 2 * helpers)
        floats = RING * p * w + helpers * RING * p * (1 + 4 * t)
        size = 8 * (words + floats)
        self.shape = zlib.crc32(f"{members},{p},{t},{w},{self.chunks},{RING}".encode())
        fd = os.open(path, os.O_RDWR | (os.O_CREAT | os.O_EXCL if create else 0), 0o600)
        try:
            if create:  # reserved now: a full /dev/shm is an OSError here, not a SIGBUS later
                os.posix_fallocate(fd, 0, size)
            elif os.fstat(fd).st_size != size:
                raise ValueError(f"{path} has {os.fstat(fd).st_size} bytes, expected {size}")
            self.map = mmap.mmap(fd, size)
        except BaseException:
            if create:
                path.unlink(missing_ok=True)
            raise
        finally:
            os.close(fd)
        ints = np.frombuffer(self.map, dtype=np.int64, count=words)
        self.header = ints[:_HEADER]
        self.joined = ints[_HEADER : _HEADER + members]
        """1 for each member that has mapped the file."""
        stamps = ints[_HEADER + members :].reshape(1 + 2 * helpers, RING, self.chunks)
        self.claims = stamps[0]
        """(RING, chunks): the stamp of the generation each chunk was last claimed for."""
        self.begin = stamps[1 : 1 + helpers]
        self.end = stamps[1 + helpers :]
        """(members - 1, RING, chunks): stamps around each member's writes of a chunk."""
        data = np.frombuffer(self.map, dtype=np.float64, offset=8 * words, count=floats)
        self.genomes = data[: RING * p * w].reshape(RING, p, w)
        rows = data[RING * p * w :].reshape(helpers, RING, p, 1 + 4 * t)
        self.fitness = rows[..., 0]
        self.components = rows[..., 1:].reshape(helpers, RING, p, t, 4)

    def close(self) -> None:
        del self.header, self.joined, self.claims, self.begin, self.end, self.genomes
        del self.fitness, self.components
        with contextlib.suppress(BufferError):  # a view still held elsewhere: the GC unmaps
            self.map.close()


class SharedTeam:
    """This worker's part in one shared team span: `generation` for the leader (the calls of
    `worker.team.Team`), `follow` for a member."""

    def __init__(self, job: Job, evaluator: Evaluator, segment: _Segment) -> None:
        self.job = job
        self.me = job.member
        self.leader = job.member == 0
        self._evaluator = evaluator
        self._segment = segment
        self._cuts = team_cuts(job.config.population, segment.chunks)
        members, chunks = len(job.team), segment.chunks
        first = self.me * chunks // members
        self._order = [(first + i) % chunks for i in range(chunks)]
        """Members start their claims spread over the generation, then go round it."""
        self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        try:
            self._socket.bind(_address(job.team_id, self.me))
        except OSError:
            self._socket.close()
            raise
        self._socket.setblocking(False)
        self._chunk_s = 0.001
        """The leader's time for its last chunk, which sets its PATIENCE with members."""
        self.taken_over = 0
        """Chunks of members the leader evaluated too (they were late)."""
        segment.joined[self.me] = 1
        self._linked = True
        """The file still has its name: the leader removes it once every member mapped it,
        or once a member given its place when the span went out has stopped trying."""
        self._unlink_at = time.monotonic() + MEMBER_WAIT_S + JOIN_GRACE_S

    @classmethod
    def join(cls, job: Job, evaluator: Evaluator) -> SharedTeam | None:
        """The leader creates the team's file; a member maps it once the leader has (None
        if it cannot within MEMBER_WAIT_S: the leader evaluates every chunk itself).

        OSError if the leader cannot create it."""
        path = segment_path(job.team_id)
        if job.member == 0:  # made whole under another name first: members map all or nothing
            draft = path.with_name(f"{path.name}.draft")
            segment = _Segment(draft, job, create=True)
            team = None
            try:
                segment.header[_SHAPE_AT] = segment.shape
                segment.header[_MAGIC_AT] = _MAGIC
                team = cls(job, evaluator, segment)
                os.replace(draft, path)
                return team
            except OSError:
                if team is not None:
                    team._socket.close()
                segment.close()
                draft.unlink(missing_ok=True)
                raise
        deadline = time.monotonic() + MEMBER_WAIT_S
        problem = "its file never appeared"
        while time.monotonic() < deadline:
            try:
                segment = _Segment(path, job, create=False)
            except FileNotFoundError:
                time.sleep(0.001)
                continue
            except (OSError, ValueError) as exc:
                problem = str(exc)
                break
            if segment.header[_MAGIC_AT] == _MAGIC and segment.header[_SHAPE_AT] == segment.shape:
                try:
                    return cls(job, evaluator, segment)
                except OSError as exc:
                    problem = str(exc)
            else:
                problem = "its file has another layout"
            segment.close()
            break
        log.warning(
            "cannot join the shared team of %s: %s; its leader evaluates everything",
            job.key.label(),
            problem,
        )
        return None

    def generation(
        self, generation: int, genomes: np.ndarray, digest: str
    ) -> tuple[np.ndarray, np.ndarray, float, int]:
        """The leader's part: publish the generation (`genomes`, of digest `digest`), evaluate
        chunks until none is left, then wait for the members' ones; fitness (n,), components
        (n, trials, 4), and the seconds and individuals evaluated here."""
        seg, slot, key = self._segment, generation % RING, stamp(generation, digest)
        if self._linked and (seg.joined.all() or time.monotonic() >= self._unlink_at):
            self._unlink()  # nobody else maps it now: nothing is left behind if killed
        seg.genomes[slot] = genomes
        seg.header[_PUBLISHED_AT] = key
        self._wake(range(1, len(self.job.team)))
        config = self.job.config
        fitness = np.empty(config.population)
        components = np.empty((config.population, config.trials, 4))
        done = np.zeros(seg.chunks, dtype=bool)
        seconds, individuals, own = 0.0, 0, 0
        for chunk in self._order:
            if seg.claims[slot, chunk] != key:
                seg.claims[slot, chunk] = key
                seconds, individuals = self._take(
                    generation, genomes, chunk, fitness, components, seconds, individuals
                )
                done[chunk], own = True, own + 1
        if own:
            self._chunk_s = seconds / own
        while True:
            for chunk in np.flatnonzero(~done).tolist():
                done[chunk] = self._read(slot, chunk, key, fitness, components)
            left = np.flatnonzero(~done).tolist()
            if not left:
                break
            if not self._sleep(PATIENCE * self._chunk_s):  # no chunk came meanwhile
                seconds, individuals = self._take(
                    generation, genomes, left[0], fitness, components, seconds, individuals
                )
                done[left[0]] = True
                self.taken_over += 1
        return fitness, components, seconds, individuals

    def _take(
        self,
        generation: int,
        genomes: np.ndarray,
        chunk: int,
        fitness: np.ndarray,
        components: np.ndarray,
        seconds: float,
        individuals: int,
    ) -> tuple[float, int]:
        """Evaluate `chunk` here into `fitness` and `components`; the leader's seconds and
        individuals with it."""
        f, c, s = self._evaluate(generation, genomes, chunk)
        a, b = self._bounds(chunk)
        fitness[a:b], components[a:b] = f, c
        return seconds + s, individuals + b - a

    def follow(self, stop: threading.Event, progress: Callable[[int, float], None]) -> None:
        """A member's part: evaluate chunks of each generation the leader publishes until the
        span's last one, the leader's leaving, `stop`, or MEMBER_WAIT_S without a generation;
        `progress(individuals, seconds)` after each generation it took chunks of.

        Raises what the evaluator raises (the leader then evaluates the chunk itself)."""
        seg, last = self._segment, self.job.key.generation + self.job.span - 1
        done_key = 0
        deadline = time.monotonic() + MEMBER_WAIT_S
        while not stop.is_set():
            key = int(seg.header[_PUBLISHED_AT])
            if seg.header[_OVER_AT]:
                return
            if key == done_key or key == 0:
                if time.monotonic() >= deadline:
                    log.info("leaving the shared team of %s: nothing heard", self.job.key.label())
                    return
                self._sleep(min(deadline - time.monotonic(), STOP_POLL_S))
                continue
            generation, slot = (key >> 32) - 1, ((key >> 32) - 1) % RING
            seconds, individuals = 0.0, 0
            for chunk in self._order:
                if stop.is_set() or seg.header[_OVER_AT] or seg.header[_PUBLISHED_AT] != key:
                    break  # the leader has moved on (or left): what is left is its own now
                if seg.claims[slot, chunk] == key:
                    continue
                seg.claims[slot, chunk] = key
                a, b = self._bounds(chunk)
                rows = np.array(seg.genomes[slot, a:b])  # its own: the slot is rewritten later
                f, c, s = self._evaluate(generation, rows, chunk, whole=False)
                region = self.me - 1
                seg.begin[region, slot, chunk] = key
                seg.fitness[region, slot, a:b] = f
                seg.components[region, slot, a:b] = c
                seg.end[region, slot, chunk] = key
                self._wake((0,))
                seconds, individuals = seconds + s, individuals + b - a
            if individuals:
                progress(individuals, seconds)
            if generation >= last:
                return
            done_key, deadline = key, time.monotonic() + MEMBER_WAIT_S

    def leave(self, generation: int) -> None:
        """From the leader: the span is over for every member (it may end before its last
        generation). A member has nothing to say: it just stops claiming chunks."""
        if self.leader:
            self._segment.header[_OVER_AT] = 1
            self._wake(range(1, len(self.job.team)))

    def close(self) -> None:
        """Unmap the file and close the socket; the leader also ends the span for its
        members and removes the file if it still has its name (mapped, it lives on until the
        last member unmaps it)."""
        if self.leader:
            self.leave(self.job.key.generation)
            if self.taken_over:
                log.info(
                    "shared team of %s: %d chunks of late members evaluated here too",
                    self.job.key.label(),
                    self.taken_over,
                )
        self._socket.close()
        self._segment.close()
        if self.leader and self._linked:
            self._unlink()

    def _unlink(self) -> None:
        with contextlib.suppress(FileNotFoundError):
            segment_path(self.job.team_id).unlink()
        self._linked = False

    def _bounds(self, chunk: int) -> tuple[int, int]:
        return self._cuts[chunk], self._cuts[chunk + 1]

    def _evaluate(
        self, generation: int, genomes: np.ndarray, chunk: int, whole: bool = True
    ) -> tuple[np.ndarray, np.ndarray, float]:
        """Fitness and components of `chunk` (of the generation's `genomes`, or of the
        chunk's rows only if not `whole`), with the seconds they took."""
        a, b = self._bounds(chunk)
        rows = genomes[a:b] if whole else genomes
        began = time.perf_counter()
        f, c = checked_evaluation(self._evaluator, self.job.config, generation, rows)
        return f, c, time.perf_counter() - began

    def _read(
        self, slot: int, chunk: int, key: int, fitness: np.ndarray, components: np.ndarray
    ) -> bool:
        """Copy `chunk` from the region of a member that wrote it for `key`, if any; the
        copy counts only if the stamps around it still say so after it."""
        seg = self._segment
        a, b = self._bounds(chunk)
        for region in np.flatnonzero(seg.end[:, slot, chunk] == key).tolist():
            fitness[a:b] = seg.fitness[region, slot, a:b]
            components[a:b] = seg.components[region, slot, a:b]
            if seg.begin[region, slot, chunk] == key and seg.end[region, slot, chunk] == key:
                return True
        return False

    def _wake(self, members: range | tuple[int, ...]) -> None:
        """A byte to each member's socket; one not listening (yet, or any more) is skipped."""
        for member in members:
            with contextlib.suppress(OSError):
                self._socket.sendto(b"!", _address(self.job.team_id, member))

    def _sleep(self, timeout: float) -> bool:
        """Wait up to `timeout` for a wake-up byte (and take any others queued); False if
        none came."""
        if timeout <= 0:
            return False
        self._socket.settimeout(timeout)
        try:
            self._socket.recv(16)
        except TimeoutError:
            return False
        finally:
            self._socket.setblocking(False)
        with contextlib.suppress(BlockingIOError):
            while True:
                self._socket.recv(16)
        return True
