"""A Dask scheduler address, checked before any work: its form, and that it answers.

``--scheduler`` takes ``local`` (a LocalCluster) or an address ``PROTOCOL://HOST:PORT`` (``HOST:PORT``
means tcp); a remote scheduler must open a TCP connection within ``CONNECT_TIMEOUT`` seconds, so that
a typo ends with a message at once instead of a hang after the first steps.
"""

from __future__ import annotations

import socket
from urllib.parse import urlsplit

CONNECT_TIMEOUT = 5.0                      # s, for a Dask scheduler to answer
SCHEDULER_PROTOCOLS = ("tcp", "tls", "ws", "wss")
DEFAULT_SCHEDULER_PORT = 8786              # Dask's

SCHEDULER_FIX = ("start the scheduler ('dask scheduler') and its workers, check the host and port "
                 "(tcp://HOST:PORT), use --scheduler local, or leave --scheduler out to run on local processes")


def parse_scheduler(address):
    """(protocol, host, port) of a Dask scheduler address (``tcp://HOST:PORT``; ``HOST:PORT`` means tcp).

    ValueError saying what is wrong with it otherwise.
    """
    text = str(address).strip()
    if not text:
        raise ValueError("an empty address")
    if "://" not in text:
        text = f"tcp://{text}"
    parts = urlsplit(text)
    if parts.scheme not in SCHEDULER_PROTOCOLS:
        raise ValueError(f"protocol '{parts.scheme}' is not one of {', '.join(SCHEDULER_PROTOCOLS)}")
    if parts.path not in ("", "/") or parts.query or parts.fragment:
        raise ValueError("an address is PROTOCOL://HOST:PORT, with nothing after the port")
    try:
        port = parts.port
    except ValueError:
        raise ValueError("the port is not a number from 1 to 65535") from None
    if not parts.hostname:
        raise ValueError("no host")
    return parts.scheme, parts.hostname, port if port else DEFAULT_SCHEDULER_PORT


def scheduler_problem(scheduler, timeout=CONNECT_TIMEOUT):
    """Why ``--scheduler`` cannot be used (in words), or None: the address is checked and, for a remote
    scheduler, a TCP connection must open within ``timeout`` s; ``local`` needs the ``distributed`` package."""
    if scheduler is None:
        return None
    import importlib.util

    if importlib.util.find_spec("distributed") is None:
        return "the Dask engine needs the 'distributed' package: pip install 'cpas_bayes[dask]'"
    if scheduler == "local":
        return None
    try:
        _, host, port = parse_scheduler(scheduler)
    except ValueError as exc:
        return f"'{scheduler}' is not a Dask scheduler address: {exc}"
    try:
        with socket.create_connection((host, port), timeout=timeout):
            pass
    except socket.timeout:
        return f"no Dask scheduler answered at {host}:{port} within {timeout:g} s"
    except OSError as exc:
        return f"no Dask scheduler reachable at {host}:{port} ({exc.strerror or exc})"
    return None
