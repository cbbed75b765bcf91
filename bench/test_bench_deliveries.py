"""One webhook delivery over HTTPS, as a job worker makes it (``service.senders.post_webhook``).

The receiver is the tests' (``harness/receivers.py``): a real HTTPS server on loopback that checks
every signature, its certificate signed by a private certificate authority the settings name
(``NARXWATCH_NOTIFICATION_CA_FILE``). Each round is a whole attempt: the target's checks, a TLS
handshake on a new connection, the signed POST and the answer. The receiver runs in this
process, so its side of the handshake is in the figure too.
"""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import pytest
import trustme

from harness.receivers import Receiver
from service.config import Settings
from service.senders import Message, post_webhook

SECRET = "whsec_" + "b" * 32


@pytest.mark.benchmark(group="notifications")
def test_webhook_delivery_over_https(benchmark, tmp_path: Path) -> None:
    authority = trustme.CA()
    authority.cert_pem.write_to_path(str(tmp_path / "ca.pem"))
    settings = Settings(
        database_url="sqlite://",
        webhook_allowed_networks=json.loads('["127.0.0.0/8"]'),
        notification_ca_file=tmp_path / "ca.pem",
    )
    message = Message("evt_1", "alarm.opened", dt.datetime.now(dt.UTC), {"id": 1, "state": "open"})
    with Receiver(SECRET, authority=authority) as receiver:
        outcome = benchmark(post_webhook, receiver.url, SECRET, 1, message, settings)
        assert outcome.delivered, outcome.error
        assert receiver.requests and all(request.signed for request in receiver.requests)
