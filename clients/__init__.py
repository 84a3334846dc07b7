"""pointfence client SDK (Python) and the wire protocol (see clients/PROTOCOL.md).

>>> from pointfence.clients import Client, Command, protocol
"""
from . import protocol
from .client import Client, ClientError, Command, LinkLost, LinkStats, Rejected, Tick, TimingError

__all__ = ["protocol", "Client", "ClientError", "Command", "LinkLost", "LinkStats", "Rejected", "Tick", "TimingError"]
