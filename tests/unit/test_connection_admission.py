"""The connection admission decision, with literal times (seconds since the epoch)."""

from __future__ import annotations

import ipaddress

from hypothesis import given
from hypothesis import strategies as st

from gateway.core.connection_admission import (
    CertificateFacts,
    ConnectionFacts,
    Door,
    NotAdmitted,
    admit,
    source_allowed,
)
from gateway.core.policy import IPAddress, IPNetwork

LOCAL = ipaddress.ip_network("127.0.0.1/32")
PLANT = ipaddress.ip_network("10.0.0.0/8")
ONE = ipaddress.ip_address("127.0.0.1")
TWO = ipaddress.ip_address("127.0.0.2")

#: A certificate valid from t=1000 to t=2000, chaining to a trusted CA.
VALID = CertificateFacts(not_before=1000.0, not_after=2000.0, trusted=True)
TLS = Door(tls=True)


def test_no_allow_list_admits_any_source_even_none() -> None:
    assert admit(Door(), ConnectionFacts(TWO), 0.0) is None
    assert admit(Door(), ConnectionFacts(None), 0.0) is None


def test_a_source_outside_the_allow_list_is_refused() -> None:
    door = Door(((LOCAL,),))
    assert admit(door, ConnectionFacts(ONE), 0.0) is None
    assert admit(door, ConnectionFacts(TWO), 0.0) is NotAdmitted.SOURCE_NOT_ALLOWED
    assert admit(door, ConnectionFacts(None), 0.0) is NotAdmitted.SOURCE_NOT_ALLOWED


def test_the_source_must_lie_in_every_list() -> None:
    """``[server] allow`` and the listener's own ``allow`` both hold."""
    door = Door(((LOCAL, PLANT), (PLANT,)))
    assert admit(door, ConnectionFacts(ONE), 0.0) is NotAdmitted.SOURCE_NOT_ALLOWED
    assert admit(door, ConnectionFacts(ipaddress.ip_address("10.1.2.3")), 0.0) is None


def test_empty_lists_do_not_count() -> None:
    assert source_allowed(((), ()), TWO)
    assert source_allowed(((), (LOCAL,)), ONE)
    assert not source_allowed(((), (LOCAL,)), TWO)


def test_at_accept_only_the_source_is_judged() -> None:
    """Before the handshake no certificate is known: the handshake checks it."""
    assert admit(TLS, ConnectionFacts(TWO), 5000.0) is None
    door = Door(((LOCAL,),), tls=True)
    assert admit(door, ConnectionFacts(TWO), 5000.0) is NotAdmitted.SOURCE_NOT_ALLOWED


def test_a_certificate_inside_its_window_is_admitted_to_the_edges() -> None:
    for now in (1000.0, 1500.0, 2000.0):
        assert admit(TLS, ConnectionFacts(ONE, True, VALID), now) is None


def test_a_certificate_expired_since_its_handshake_is_refused() -> None:
    """Valid at the handshake (t=1500), expired at the reload (t=2000.5)."""
    facts = ConnectionFacts(ONE, True, VALID)
    assert admit(TLS, facts, 1500.0) is None
    assert admit(TLS, facts, 2000.5) is NotAdmitted.CERTIFICATE_EXPIRED


def test_a_certificate_not_yet_valid_is_refused() -> None:
    assert admit(TLS, ConnectionFacts(ONE, True, VALID), 999.0) is (
        NotAdmitted.CERTIFICATE_NOT_YET_VALID
    )


def test_a_chain_to_a_withdrawn_ca_is_refused() -> None:
    untrusted = CertificateFacts(1000.0, 2000.0, trusted=False)
    assert admit(TLS, ConnectionFacts(ONE, True, untrusted), 1500.0) is NotAdmitted.CA_NOT_TRUSTED


def test_a_revoked_certificate_is_refused_after_trust_and_before_dates() -> None:
    revoked = CertificateFacts(1000.0, 2000.0, trusted=True, revoked=True)
    assert admit(TLS, ConnectionFacts(ONE, True, revoked), 1500.0) is (
        NotAdmitted.CERTIFICATE_REVOKED
    )
    assert admit(TLS, ConnectionFacts(ONE, True, revoked), 3000.0) is (
        NotAdmitted.CERTIFICATE_REVOKED
    )
    untrusted = CertificateFacts(1000.0, 2000.0, trusted=False, revoked=True)
    assert admit(TLS, ConnectionFacts(ONE, True, untrusted), 1500.0) is NotAdmitted.CA_NOT_TRUSTED
    assert admit(TLS, ConnectionFacts(ONE, False, revoked), 1500.0) is None  # at accept


def test_an_established_tls_connection_without_certificate_is_refused() -> None:
    assert admit(TLS, ConnectionFacts(ONE, True, None), 1500.0) is NotAdmitted.NO_CERTIFICATE


def test_the_order_source_then_trust_then_dates() -> None:
    """A connection failing several checks is refused for the first, in the documented order."""
    everything_wrong = CertificateFacts(1000.0, 2000.0, trusted=False)
    door = Door(((LOCAL,),), tls=True)
    assert admit(door, ConnectionFacts(TWO, True, everything_wrong), 3000.0) is (
        NotAdmitted.SOURCE_NOT_ALLOWED
    )
    assert admit(door, ConnectionFacts(ONE, True, everything_wrong), 3000.0) is (
        NotAdmitted.CA_NOT_TRUSTED
    )


def test_a_plain_listener_ignores_certificates() -> None:
    untrusted = CertificateFacts(1000.0, 2000.0, trusted=False)
    assert admit(Door(), ConnectionFacts(ONE, True, untrusted), 9999.0) is None


# -- invariants ------------------------------------------------------------------------

addresses = st.integers(0x7F000000, 0x7F0000FF).map(ipaddress.IPv4Address)
networks = st.builds(
    lambda address, prefix: ipaddress.ip_network(f"{address}/{prefix}", strict=False),
    addresses,
    st.integers(24, 32),
)
network_lists = st.lists(st.lists(networks, max_size=3).map(tuple), max_size=2).map(tuple)
certificates = st.builds(
    CertificateFacts,
    st.floats(0, 1000, allow_nan=False),
    st.floats(0, 1000, allow_nan=False),
    st.booleans(),
)


@given(
    network_lists,
    st.lists(networks, max_size=2),
    st.one_of(st.none(), addresses),
    st.booleans(),
    st.one_of(st.none(), certificates),
    st.floats(0, 1000, allow_nan=False),
)
def test_a_wider_door_admits_whatever_a_narrower_one_admits(
    lists: tuple[tuple[IPNetwork, ...], ...],
    wider_by: list[IPNetwork],
    source: IPAddress | None,
    tls: bool,
    certificate: CertificateFacts | None,
    now: float,
) -> None:
    narrow = Door(lists, tls)
    wide = Door(tuple((*networks, *wider_by) if networks else () for networks in lists), tls)
    facts = ConnectionFacts(source, True, certificate)
    if admit(narrow, facts, now) is None:
        assert admit(wide, facts, now) is None


@given(certificates, st.floats(0, 1000, allow_nan=False))
def test_trusting_more_never_refuses_more(certificate: CertificateFacts, now: float) -> None:
    trusted = CertificateFacts(certificate.not_before, certificate.not_after, trusted=True)
    if admit(TLS, ConnectionFacts(ONE, True, certificate), now) is None:
        assert admit(TLS, ConnectionFacts(ONE, True, trusted), now) is None
