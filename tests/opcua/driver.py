"""A foreign OPC UA client for holarchy's `cell opcua` tests (Python asyncua 2.1).

Connects to URL, then reads commands from stdin, one per line, and answers each with one
JSON line on stdout, so that the Rust test (tests/tests/opcua.rs) plays the scenario and
checks the cell's side (simulator counts, orders) between the steps.

    driver.py URL CELL [--user NAME --password PW] [--secure CERTDIR]

--secure CERTDIR: SignAndEncrypt with Basic256Sha256, the client application
certificate CERTDIR/client.der (+ client-key.pem), made on first use (self-signed, RSA
2048, ApplicationUri and common name urn:holarchy:test-client).

The first line out is {"connected": true} or {"connected": false, "status": "<Bad...>"}.
Commands:
    browse                          -> {"resources": [...]} (Objects/PackMLObjects)
    read RES PATH                   -> {"value": ...}  PATH e.g. Status.StateCurrent
    readcell PATH                   -> {"value": ...}  e.g. OrdersDone, Security.LoginsRefused
    call RES METHOD [INT]           -> {"status": "Good" | "Bad..."}
    submit PRODUCT COUNT PRIORITY [SUBMIT_ID] -> {"status": ..., "orders": [...]}  (PRODUCT may hold \n)
    subscribe RES PATH              -> {"status": "Good"} (publishing interval 20 ms)
    changes                         -> {"values": [...], "latency_ms": [...]} since start
                                       (latency: SourceTimestamp to receipt, initial values left out)
    quit
"""

import asyncio
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
        return type(error).__name__ + ": " + str(error)
    try:
        return ua.StatusCode(code).name
    except Exception:
        return str(code)


class Changes:
    """Every value a subscription delivered and, for each change after a monitored
    item's first (initial) value, the time from the server's SourceTimestamp to here."""

    def __init__(self):
        self.values = []
        self.latency_ms = []
        self.seen = set()

    def datachange_notification(self, node, val, data):
        now = time.time()
        self.values.append(val)
        first = node.nodeid not in self.seen
        self.seen.add(node.nodeid)
        source = data.monitored_item.Value.SourceTimestamp
        if source is not None and not first:
            self.latency_ms.append(round((now - source.timestamp()) * 1000.0, 1))


async def main():
    args = sys.argv[1:]
    url, cell = args[0], args[1]
    opts = dict(zip(args[2::2], args[3::2]))
    client = Client(url=url, timeout=8)
    client.application_uri = APP_URI
    if "--secure" in opts:
        certdir = opts["--secure"]
        os.makedirs(certdir, exist_ok=True)
        cert, key = Path(certdir) / "client.der", Path(certdir) / "client-key.pem"
        # Self-signed; its common name is the ApplicationUri.
        await setup_self_signed_certificate(
            key, cert, APP_URI, "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH], {}
        )
        await client.set_security_string(f"Basic256Sha256,SignAndEncrypt,{cert},{key}")
    if "--user" in opts:
        client.set_user(opts["--user"])
        client.set_password(opts.get("--password", ""))
    try:
        await client.connect()
    except Exception as e:
        print(json.dumps({"connected": False, "status": status_name(e)}), flush=True)
        return
    print(json.dumps({"connected": True}), flush=True)
    idx = await client.get_namespace_index(f"urn:holarchy:{cell}")
    objects = client.nodes.objects
    changes = Changes()
    subscription = None
    loop = asyncio.get_running_loop()
    try:
        while True:
            line = await loop.run_in_executor(None, sys.stdin.readline)
            if not line:
                break
            words = line.split()
            if not words:
                continue
            command, rest = words[0], words[1:]
            out = {}
            try:
                if command == "quit":
                    break
                elif command == "browse":
                    folder = await objects.get_child([f"{idx}:PackMLObjects"])
                    # One Browse: the names come with the references (a resource
                    # removed meanwhile cannot fail a second read).
                    names = [d.BrowseName.Name for d in await folder.get_children_descriptions()]
                    out = {"resources": sorted(names)}
                elif command == "read":
                    path = [f"{idx}:PackMLObjects", f"{idx}:{rest[0]}"] + [f"{idx}:{p}" for p in rest[1].split(".")]
                    node = await objects.get_child(path)
                    value = await node.read_value()
                    out = {"value": value.isoformat() if hasattr(value, "isoformat") else value}
                elif command == "readcell":
                    node = await objects.get_child([f"{idx}:Cell"] + [f"{idx}:{p}" for p in rest[0].split(".")])
                    out = {"value": await node.read_value()}
                elif command == "call":
                    node = await objects.get_child([f"{idx}:PackMLObjects", f"{idx}:{rest[0]}"])
                    arguments = [ua.Variant(int(a), ua.VariantType.Int32) for a in rest[2:]]
                    await node.call_method(f"{idx}:{rest[1]}", *arguments)
                    out = {"status": "Good"}
                elif command == "submit":
                    node = await objects.get_child([f"{idx}:Cell"])
                    # \n and the like in the product name are sent as the characters.
                    product = rest[0].encode().decode("unicode_escape")
                    arguments = [
                        ua.Variant(product, ua.VariantType.String),
                        ua.Variant(int(rest[1]), ua.VariantType.Int32),
                        ua.Variant(int(rest[2]), ua.VariantType.Int32),
                    ]
                    # An optional fourth word: the work order's submitId.
                    if len(rest) > 3:
                        arguments.append(ua.Variant(rest[3], ua.VariantType.String))
                    orders = await node.call_method(f"{idx}:SubmitWorkOrder", *arguments)
                    out = {"status": "Good", "orders": orders}
                elif command == "subscribe":
                    path = [f"{idx}:PackMLObjects", f"{idx}:{rest[0]}"] + [f"{idx}:{p}" for p in rest[1].split(".")]
                    node = await objects.get_child(path)
                    if subscription is None:
                        subscription = await client.create_subscription(20, changes)
                    await subscription.subscribe_data_change(node)
                    out = {"status": "Good"}
                elif command == "changes":
                    out = {"values": changes.values, "latency_ms": changes.latency_ms}
                else:
                    out = {"status": "unknown command " + command}
            except ua.UaStatusCodeError as e:
                out = {"status": status_name(e), "orders": []}
            except Exception as e:
                out = {"status": status_name(e), "orders": []}
            print(json.dumps(out, default=str), flush=True)
    finally:
        await client.disconnect()


asyncio.run(main())
