"""The redundancy pair's I/O shell: the role machine fed with time and evidence, obeyed.

Theory of operation. Every decision is ``core.redundancy.RoleMachine``'s. This shell
feeds it the boot-time clock (``CLOCK_BOOTTIME``: it counts a suspend, so a lease never
outlives one), the peer's ``/role`` (``channel.PeerPoller``) and the bus's evidence
(each line's ``PairedLine`` reports the master frames it did not send and the bytes it
heard), and carries out what the machine decides:

* The lines transmit only while the machine says so: each line asks ``may_transmit``
  right before every frame it writes. A frame refused is not written (never a frame on
  someone else's lease): the line pauses and answers what it held on the wire 0x0A at
  once (``Bus.refused``), and the machine, told the time, steps down.
* Active: every line takes its masters' requests; a line that sent nothing for half a
  lease reads one holding register (``keepalive``) so that the standby hears the bus alive.
* Standby: the lines only listen (their learning goes on from what they hear) and every
  request is forwarded to the peer's Modbus listener (``forward``), or answered 0x0A
  while the peer is not active either, or when it comes from the peer itself (no loops).
"""

from __future__ import annotations

import asyncio
import logging
import secrets
import struct
import time
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING

from ...config import MetricsConfig, RedundancyConfig
from ...core import pdu as fc
from ...core.line import LineRequest
from ...core.outcome import Outcome
from ...core.redundancy import HEARING_DELAY_S, ChangeReason, Role, RoleMachine
from ...core.routes import RouteTable
from ..line.bus import Bus
from ..status import PairStatus
from .channel import PeerPoller, PeerRole, peer_tls, role_body
from .line import PairedLine, keepalive_slave

if TYPE_CHECKING:
    from ...metrics import GatewayMetrics
    from .forward import PeerForwarder

log = logging.getLogger("gateway.pair")


def boot_time() -> float:
    """Seconds since boot, suspend included: the clock of every lease."""
    return time.clock_gettime(time.CLOCK_BOOTTIME)


class KeepAliveMaster:
    """The master a keep-alive read is queued for: the gateway itself."""

    peer = "keep-alive"

    def __repr__(self) -> str:
        return "<keep-alive>"


class Pair:
    """One gateway of an active/standby pair (see the module doc)."""

    def __init__(
        self,
        config: RedundancyConfig,
        endpoint: MetricsConfig,
        buses: Mapping[str, Bus],
        forwarder: PeerForwarder,
        metrics: GatewayMetrics,
        clock: Callable[[], float] = boot_time,
    ) -> None:
        assert config.peer is not None
        self.config = config
        self._clock = clock
        self.machine = RoleMachine(
            config.priority, start=clock(), lease=config.lease,
            takeover_after=config.takeover_after, hearing_delay=HEARING_DELAY_S,
            keepalive=config.keepalive is not None,
            tiebreak=secrets.randbits(32),  # separates equal priorities (``Contest``)
        )  # fmt: skip
        self.buses = buses
        self.forwarder = forwarder
        self._metrics = metrics
        metrics.watch_forwarding(forwarder.stats.by_outcome)
        self._keepalive_master = KeepAliveMaster()
        self._peer_hosts = config.peer_hosts
        self._timer: asyncio.TimerHandle | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._applied: Role | None = None
        self._peer: PeerRole | None = None  # the peer's last /role, None while unreachable
        self._warned_equal = False
        self.poller = PeerPoller(
            config.peer,
            interval=config.lease / 4,
            timeout=config.lease / 2,
            on_role=self._peer_role,
            on_unreachable=self._peer_unreachable,
            token=endpoint.status_token,
            tls=peer_tls(endpoint.tls_cert, endpoint.tls_key, endpoint.tls_ca),
            clock=clock,
        )

    # -- lifecycle ------------------------------------------------------------------------

    def line_role(self) -> PairedLine:
        """The role a line of this gateway plays (``Bus``'s ``role``): its port opens
        driving nothing, its lease check and evidence come here."""
        return PairedLine(self)

    def attach(self, bus: Bus) -> None:
        """A line about to open (at start or reopened by a reload), built with
        ``line_role()``: it opens listening, and takes the pair's role."""
        if self._applied is Role.ACTIVE:
            bus.activate()
        else:
            bus.stand_by(self._forward_for(bus.name))

    def start(self) -> None:
        """Begin as standby: the lines listen until the machine says otherwise."""
        self._loop = asyncio.get_running_loop()
        self._pump()
        self.poller.start()

    async def stop(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        await self.poller.stop()
        self.forwarder.close()

    def reroute(self, table: RouteTable) -> None:
        """The routing table the active's admission runs (at start, and each reload's new
        one): forwarding sends each request under the unit id this table gives its slave."""
        self.forwarder.reroute(table.units)

    # -- what the rest of the gateway asks ------------------------------------------------

    @property
    def standing_by(self) -> bool:
        """This gateway listens and forwards (``/readyz`` says so)."""
        return self.machine.role is Role.STANDBY

    def may_transmit(self) -> bool:
        """The lease check before every frame (each line's ``PairedLine``)."""
        now = self._clock()
        if self.machine.may_transmit(now):
            self.machine.transmitted(now)
            return True
        self._metrics.redundancy_refused_frames.inc()
        if self._loop is not None:
            self._loop.call_soon(self._after_refusal)
        return False

    def role_body(self) -> tuple[int, bytes]:
        """``/role``: 200 while active, 503 while standby, with the JSON document."""
        report = self.machine.report(self._clock())
        body = role_body(report.role, report.lease_remaining, report.priority, True,
                         report.peer_lease_remaining)  # fmt: skip
        return (200 if report.role is Role.ACTIVE else 503), body

    def status(self) -> PairStatus:
        """For /status and the status page."""
        assert self.config.peer is not None
        host, port = self.config.peer
        peer = self._peer
        return PairStatus(
            role=self.machine.role.value,
            lease_remaining=round(self.machine.lease_remaining(self._clock()), 3),
            priority=self.config.priority,
            peer=f"{host}:{port}",
            peer_role=None if peer is None else peer.role.value,
        )

    # -- evidence -------------------------------------------------------------------------

    def master_frame_heard(self) -> None:
        """A line heard a master frame it did not send."""
        self.machine.master_frame_heard(self._clock())
        self._pump()

    def frame_heard(self) -> None:
        """A line heard bytes: the bus is busy (a lapsed lease may show here first)."""
        self.machine.frame_heard(self._clock())
        if self.machine.changes:
            self._pump()

    def _peer_role(self, peer: PeerRole) -> None:
        if peer.priority == self.config.priority and not self._warned_equal:
            self._warned_equal = True
            log.warning(
                "pair: the peer has this gateway's priority (%d): started together, they "
                "take over together once before a random draw separates them; give them "
                "different [redundancy] priority values", peer.priority,
            )  # fmt: skip
        self._peer = peer
        self.machine.peer_report(self._clock(), peer.role, peer.lease_remaining, peer.priority,
                                 peer.peer_lease_remaining, peer.asked_at)  # fmt: skip
        self.forwarder.peer_active = peer.role is Role.ACTIVE
        self._pump()

    def _peer_unreachable(self, _why: str) -> None:
        self._peer = None
        self.machine.peer_unreachable(self._clock())
        self.forwarder.peer_active = False
        self._pump()

    # -- carrying out ---------------------------------------------------------------------

    def _after_refusal(self) -> None:
        """A line's frame was refused (``may_transmit``): the machine, told the time, steps
        down (the lease lapsed, or the clock jumped) and the lines stand by. Should it still
        hold a lease by then, the lines the refusal paused resume."""
        now = self._clock()
        self.machine.handle_timer(now)
        self._pump()
        if self.machine.may_transmit(now):
            for bus in self.buses.values():
                if bus.refused:
                    bus.activate()

    def _on_timer(self) -> None:
        self._timer = None
        self.machine.handle_timer(self._clock())
        self._pump()

    def _pump(self) -> None:
        """Carry out the machine's actions, in the order the timer always took them (a
        keep-alive, then the role changes: each logged and counted, the lines set to the
        role), then arm its timer."""
        machine = self.machine
        if machine.keepalives:
            machine.keepalives.clear()  # one read per line, however many were asked for
            self._keep_alive()
        for change in machine.drain_changes():
            log.warning("pair: now %s (%s)", change.role.value, _REASONS[change.reason])
            if change.role is Role.ACTIVE:
                self._metrics.redundancy_takeovers.inc()
        role = self.machine.role
        if role is not self._applied:
            self._applied = role
            self._metrics.redundancy_role.set(1 if role is Role.ACTIVE else 0)
            for bus in self.buses.values():
                if role is Role.ACTIVE:
                    bus.activate()
                else:
                    bus.stand_by(self._forward_for(bus.name))
        self._arm()

    def _arm(self) -> None:
        loop = self._loop
        if loop is None:
            return
        delay = min(max(self.machine.get_timer() - self._clock(), 0.0), self.config.lease / 4)
        if self._timer is not None:
            self._timer.cancel()
        self._timer = loop.call_later(delay, self._on_timer)

    def _forward_for(self, line: str) -> Callable[[LineRequest], bool]:
        forwarder = self.forwarder
        peer_hosts = self._peer_hosts

        def forward(request: LineRequest) -> bool:
            source = getattr(request.master, "source", None)
            if source in peer_hosts:  # the peer forwarding to us while we stand by: no loop
                Bus.answer_unavailable([request])
                return True
            return forwarder.submit(line, request)

        return forward

    def _keep_alive(self) -> None:
        """A one-register read on every line that has a slave to read (``keepalive``)."""
        target = self.config.keepalive
        if target is None:
            return
        for bus in self.buses.values():
            slave, register = target if target != (0, 0) else (keepalive_slave(bus), 0)
            if not slave or not bus.idle:
                continue
            pdu = struct.pack(">BHH", fc.READ_HOLDING_REGISTERS, register, 1)
            bus.submit(LineRequest(slave, pdu, self._keepalive_master, _ignore))


_REASONS = {
    ChangeReason.TAKEOVER: "the peer's lease expired, the peer is not active and the bus "
    "stayed quiet: taking over",
    ChangeReason.ANOTHER_MASTER: "heard a master frame this gateway did not send: silent "
    "while another master transmits",
    ChangeReason.PEER_ACTIVE: "the peer answers as active",
    ChangeReason.LEASE_EXPIRED: "the lease ran out without evidence to renew it",
    ChangeReason.TIME_JUMP: "the clock jumped (the process was frozen or the machine "
    "suspended): the lease is stale",
}


def _ignore(_pdu: bytes, _outcome: Outcome) -> None:
    """A keep-alive's answer matters only as traffic on the bus."""


__all__: Sequence[str] = ("Pair", "boot_time")
