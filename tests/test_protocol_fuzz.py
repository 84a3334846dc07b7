"""Fuzzing the service's packet handler (the receiver's code path) with hypothesis: >= 50,000 random
and mutated datagrams; none raises, none forged is accepted, none changes the master's sample.
(1,000,000 datagrams: `pointfence bench fuzz`.)"""
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pointfence.bench.fuzz import Fuzzer
from pointfence.clients import protocol as P

BATCH = 100
EXAMPLES = 520     # x 100 = 52,000 datagrams from seeds, plus the raw-bytes examples below


class _Tally:
    packets = 0


@settings(max_examples=EXAMPLES, deadline=None, database=None, suppress_health_check=list(HealthCheck))
@given(seed=st.integers(min_value=0, max_value=2**63))
def test_random_and_mutated_datagrams_are_refused(seed):
    fz = Fuzzer(seed)
    try:
        for _ in range(BATCH):
            fz.one()
        assert fz.accepted_forgeries == 0
        assert fz.master_changed == 0
        _Tally.packets += fz.count
    finally:
        fz.close()


_raw = Fuzzer(12345)


@settings(max_examples=2000, deadline=None, database=None, suppress_health_check=list(HealthCheck))
@given(data=st.binary(min_size=0, max_size=400), typ=st.integers(1, 7), header=st.booleans())
def test_hypothesis_bytes_are_refused(data, typ, header):
    fz = _raw
    if header:   # make it look right: magic, version, the live session, exact size
        size = P.SIZES[typ]
        data = (data * (size // max(len(data), 1) + 1))[:size] if data else bytes(size)
        data = P.HEADER.pack(P.MAGIC, P.VERSION, typ, fz.session.device_id, fz.session.id, 2**40, 0) + data[P.HEADER_LEN:]
    before = fz.sample()
    assert fz.hub.handle(data, fz.addr) != P.E_OK
    assert fz.sample() == before
    _Tally.packets += 1


def test_at_least_50000_datagrams_were_thrown():
    assert _Tally.packets >= 50_000, _Tally.packets
