"""A stranger on the plant network, against holarchy's `cell opcua` (Python asyncua 2.1),
for tests/tests/opcua_attacks.rs. Each mode does one attack and prints one JSON line.

    attacker.py mkcert CERTDIR
        makes the client application certificate CERTDIR/client.der (+ client-key.pem),
        as tests/opcua/driver.py does, and prints {"certificate": PATH}
    attacker.py sessions URL N [--from ADDR]
        one channel of SecurityPolicy None, N CreateSession on it
        -> {"statuses": [...]}
    attacker.py channel URL POLICY MODE CERTDIR [--from ADDR]
        opens a channel of POLICY (Basic128Rsa15, Basic256, Basic256Sha256, ...) and MODE
        (Sign, SignAndEncrypt) and creates a session on it -> {"status": ...}
    attacker.py pending URL CERTDIR N [--from ADDR]
        one trusted SignAndEncrypt channel, N CreateSession without activating any
        -> {"statuses": [...]}; then holds the channel open until stdin closes
    attacker.py guess URL CERTDIR USER N PARALLEL [--from ADDR] [--spread]
        N logins of USER with wrong passwords (the last one with the password given by
        $RIGHT_PASSWORD, if set), PARALLEL connections at once; --spread: connection i
        comes from 127.0.0.(2+i) and guesses the name USER-i (many guessers, many names)
        -> {"statuses": {status: count}, "last": status, "seconds": s}

$SERVER_CERT: the server's certificate (DER); with it the channel is opened as asked, not
chosen from the server's endpoints.
--from ADDR: the client's source address (a loopback address such as 127.0.0.2, so that
one machine plays a stranger and an operator).
"""

import asyncio
import collections
import json
import os
import sys
import time
from pathlib import Path

from asyncua import Client, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from cryptography.x509.oid import ExtendedKeyUsageOID

APP_URI = "urn:holarchy:test-client"


def status_name(error):
    code = getattr(error, "code", None)
    if code is None:
        text = type(error).__name__ + ": " + str(error)
        # A server's ERR message arrives as a connection closed with its status.
        for word in str(error).replace("(", " ").replace(")", " ").replace(",", " ").split():
            if word.startswith("Bad"):
                return word
        return text
    try:
        return ua.StatusCode(code).name
    except Exception:
        return str(code)


def bind_from(address):
    """Every connection of this process comes from `address`."""
    if not address:
        return
    loop_class = asyncio.get_event_loop_policy().get_event_loop().__class__
    original = loop_class.create_connection

    async def create_connection(self, factory, host=None, port=None, **kw):
        kw.setdefault("local_addr", (address, 0))
        return await original(self, factory, host, port, **kw)

    loop_class.create_connection = create_connection


async def certificate(certdir):
    os.makedirs(certdir, exist_ok=True)
    cert, key = Path(certdir) / "client.der", Path(certdir) / "client-key.pem"
    await setup_self_signed_certificate(
        key, cert, APP_URI, "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH], {}
    )
    return cert, key


async def secure_client(url, certdir, policy="Basic256Sha256", mode="SignAndEncrypt"):
    cert, key = await certificate(certdir)
    client = Client(url=url, timeout=8)
    client.application_uri = APP_URI
    server = os.environ.get("SERVER_CERT")
    if server:
        # The server's certificate given: no endpoint is asked for, so a policy or mode
        # the server does not offer is really tried on the wire.
        from asyncua.crypto import security_policies

        name = "SecurityPolicy" + policy.replace("_", "")
        await client.set_security(
            getattr(security_policies, name), str(cert), str(key),
            server_certificate=server, mode=getattr(ua.MessageSecurityMode, mode),
        )
    else:
        await client.set_security_string(f"{policy},{mode},{cert},{key}")
    return client


async def open_channel(client):
    await client.connect_socket()
    await client.send_hello()
    await client.open_secure_channel()


async def create_sessions(client, n):
    """N CreateSession on the client's channel, none activated: their statuses."""
    statuses = []
    for _ in range(n):
        try:
            await client.create_session()
            statuses.append("Good")
        except Exception as e:
            statuses.append(status_name(e))
    return statuses


async def sessions(url, n):
    client = Client(url=url, timeout=8)
    client.application_uri = APP_URI
    try:
        await open_channel(client)
    except Exception as e:
        return {"statuses": ["channel: " + status_name(e)]}
    statuses = await create_sessions(client, n)
    client.disconnect_socket()
    return {"statuses": statuses}


async def channel(url, policy, mode, certdir):
    try:
        client = await secure_client(url, certdir, policy, mode)
    except Exception as e:
        return {"status": "client: " + status_name(e)}
    try:
        await open_channel(client)
        await client.create_session()
        status = "Good"
    except Exception as e:
        status = status_name(e)
    client.disconnect_socket()
    return {"status": status}


async def pending(url, certdir, n):
    client = await secure_client(url, certdir)
    await open_channel(client)
    statuses = await create_sessions(client, n)
    print(json.dumps({"statuses": statuses}), flush=True)
    loop = asyncio.get_running_loop()
    await loop.run_in_executor(None, sys.stdin.read)
    client.disconnect_socket()
    return None


async def one_login(url, certdir, user, password):
    client = await secure_client(url, certdir)
    client.set_user(user)
    client.set_password(password)
    try:
        await client.connect()
        await client.disconnect()
        return "Good"
    except Exception as e:
        client.disconnect_socket()
        return status_name(e)


async def guess(url, certdir, user, n, parallel, spread):
    await certificate(certdir)
    right = os.environ.get("RIGHT_PASSWORD")
    counts = collections.Counter()
    last = None
    queue = asyncio.Queue()
    for i in range(n):
        queue.put_nowait(i)

    async def guesser(g):
        nonlocal last
        name = f"{user}-{g}" if spread else user
        while True:
            try:
                i = queue.get_nowait()
            except asyncio.QueueEmpty:
                return
            password = right if (right and i == n - 1) else f"guess-{i}"
            status = await one_login(url, certdir, name, password)
            counts[status] += 1
            if i == n - 1:
                last = status

    start = time.monotonic()
    if spread:
        # Each guesser from its own address: one process per address.
        procs = []
        per = max(1, n // parallel)
        for g in range(parallel):
            procs.append(
                await asyncio.create_subprocess_exec(
                    sys.executable, sys.argv[0], "guess", url, certdir, f"{user}-{g}",
                    str(per), "1", "--from", f"127.0.0.{2 + g}",
                    stdout=asyncio.subprocess.PIPE,
                )
            )
        for p in procs:
            out, _ = await p.communicate()
            answer = json.loads(out.decode().strip().splitlines()[-1])
            counts.update(answer["statuses"])
    else:
        await asyncio.gather(*(guesser(g) for g in range(parallel)))
    return {"statuses": dict(counts), "last": last, "seconds": round(time.monotonic() - start, 2)}


async def main():
    args = sys.argv[1:]
    source = None
    if "--from" in args:
        at = args.index("--from")
        source = args[at + 1]
        del args[at : at + 2]
    spread = "--spread" in args
    args = [a for a in args if a != "--spread"]
    bind_from(source)
    mode = args[0]
    if mode == "mkcert":
        cert, _ = await certificate(args[1])
        out = {"certificate": str(cert)}
    elif mode == "sessions":
        out = await sessions(args[1], int(args[2]))
    elif mode == "channel":
        out = await channel(args[1], args[2], args[3], args[4])
    elif mode == "pending":
        out = await pending(args[1], args[2], int(args[3]))
    elif mode == "guess":
        out = await guess(args[1], args[2], args[3], int(args[4]), int(args[5]), spread)
    else:
        out = {"error": "unknown mode " + mode}
    if out is not None:
        print(json.dumps(out), flush=True)


asyncio.run(main())
