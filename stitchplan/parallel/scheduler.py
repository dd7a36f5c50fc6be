"""A Dask scheduler's address, checked by its form, and reaching the scheduler there within a deadline."""

from __future__ import annotations

import ipaddress
import re
from typing import Any

from ..errors import InputError

CONNECT_TIMEOUT_S = 5.0  # reaching a --scheduler and hearing its answer, at most this long
# distributed's comm schemes that reach a scheduler in another process (inproc:// is in-process
# only; ucx:// has left distributed for distributed-ucxx)
SCHEDULER_SCHEMES = ("tcp", "tls", "ws", "wss")
SCHEDULER_EXPECTED = ("a Dask scheduler address SCHEME://HOST:PORT with SCHEME tcp, tls, ws or wss and PORT "
                      "from 1 to 65535, such as tcp://127.0.0.1:8786")
_HOST_NAME = re.compile(r"[A-Za-z0-9_]([A-Za-z0-9_.-]*[A-Za-z0-9_])?")  # a host name or an IPv4 address


def check_scheduler_address(address: str) -> tuple[str, int]:
    """SCHEME://HOST:PORT as distributed's comm layer reads it (distributed.comm.addressing:
    parse_address, parse_host_port), checked here so that a malformed address is an InputError
    before any work: a scheme of SCHEDULER_SCHEMES, a host name, IPv4 address or bracketed IPv6
    address, a port from 1 to 65535, nothing else. Returns (host, port)."""
    try:
        return _host_port(address)
    except ValueError as problem:
        raise InputError(f"--scheduler: got {address!r}, expected {SCHEDULER_EXPECTED} ({problem})") from None


def _host_port(address: str) -> tuple[str, int]:
    """(host, port) of SCHEME://HOST:PORT; a ValueError saying what is wrong otherwise."""
    scheme, sep, location = address.partition("://")
    if not sep:
        raise ValueError("no scheme")
    if scheme not in SCHEDULER_SCHEMES:
        raise ValueError(f"unknown scheme {scheme!r}")
    if location.startswith("["):  # IPv6: [addr]:port
        host, bracket, tail = location[1:].partition("]")
        if not bracket:
            raise ValueError("no ']' after the IPv6 host")
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            raise ValueError(f"{host!r} is not an IPv6 address") from None
        if not tail:
            raise ValueError("no port")
        if not tail.startswith(":"):
            raise ValueError(f"{tail!r} after the host, expected :PORT")
        port = tail[1:]
    else:
        host, colon, port = location.rpartition(":")
        if not colon:
            raise ValueError("no port" if location else "no host")
        if ":" in host:
            raise ValueError("an IPv6 host needs brackets, such as tcp://[::1]:8786")
        if not host:
            raise ValueError("no host")
        if not _HOST_NAME.fullmatch(host):
            raise ValueError(f"host {host!r} is not a host name or an IP address")
    if not (port.isascii() and port.isdigit()):
        raise ValueError(f"port {port!r} is not a number" if port else "no port")
    if not 1 <= int(port) <= 65535:
        raise ValueError(f"port {int(port)} is out of range")
    return host, int(port)


def probe_scheduler(address: str, timeout: float | None = None) -> None:
    """Connect to `address` and ask who is there (distributed's `identity` message), within
    `timeout` seconds (CONNECT_TIMEOUT_S) in all: an InputError naming --scheduler unless a
    Dask scheduler answers. distributed.Client bounds the connection itself by its `timeout`
    but not the handshake that follows, which a server that never answers holds forever."""
    import asyncio

    from distributed.comm import connect
    from distributed.security import Security

    timeout = CONNECT_TIMEOUT_S if timeout is None else timeout
    expected = "expected the address of a running `dask scheduler`"

    connecting = 0.8 * timeout  # the rest of the deadline is for the handshake and the answer

    async def identity() -> Any:
        # distributed's connect() retries for its `timeout`, then raises a plain OSError
        comm = await connect(address, timeout=connecting, **Security().get_connection_args("client"))
        try:
            await comm.write({"op": "identity", "reply": True})
            return await comm.read()
        finally:
            comm.abort()

    try:
        reply = asyncio.run(asyncio.wait_for(identity(), timeout))
    except TimeoutError:  # the deadline (asyncio.TimeoutError is TimeoutError)
        raise InputError(f"--scheduler: no answer from {address} within {timeout:g} s; {expected}") from None
    except Exception as error:  # noqa: BLE001 -- whatever a server that is not a scheduler makes of it
        if type(error) is OSError:  # connect() gave up: nothing listening, or the host unreachable
            why = _why_unreachable(address, timeout - connecting) or brief_error(_last_cause(error))
            raise InputError(f"--scheduler: cannot connect to {address} within {timeout:g} s ({why}); "
                             f"{expected}") from None
        # a MemoryError: Dask's frame reader took another protocol's bytes (a banner) for a length
        read = ("it is not Dask's protocol: its first bytes read as the length of a message too long to hold"
                if isinstance(error, MemoryError) else brief_error(error))
        raise InputError(f"--scheduler: {address} does not answer as a Dask scheduler (its reply could "
                         f"not be read: {read}); {expected}") from None
    kind = reply.get("type") if isinstance(reply, dict) else None
    if kind != "Scheduler":
        what = f"a Dask {kind}" if isinstance(kind, str) else f"a reply of type {type(reply).__name__}"
        raise InputError(f"--scheduler: {address} answers as {what}, not a scheduler; {expected}")


def _why_unreachable(address: str, timeout: float) -> str | None:
    """Why a TCP connection to the address fails (refused, unknown host, timed out), from one
    plain attempt; None if it succeeds. distributed's connect() keeps only its last attempt's
    error, often a timeout of an attempt cut short by its deadline."""
    import socket

    try:
        with socket.create_connection(check_scheduler_address(address), timeout=max(timeout, 0.1)):
            return None
    except OSError as error:
        return brief_error(error)


def _last_cause(error: BaseException) -> BaseException:
    """The error at the bottom of `error`'s chain of causes (the refused connection, the
    unknown host), not distributed's wrappers of it."""
    while error.__cause__ is not None:
        error = error.__cause__
    return error


def brief_error(error: BaseException) -> str:
    """`Type: the message on one line`, short enough for the one error line (without the
    `in <distributed.comm...>: ` that distributed puts before the message it wraps)."""
    text = re.sub(r"^in <[^>]*>: ", "", " ".join(str(error).split()))
    text = f"{type(error).__name__}: {text}" if text else type(error).__name__
    return text if len(text) <= 200 else text[:197] + "..."
