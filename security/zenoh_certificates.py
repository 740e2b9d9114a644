"""The secured bus's TLS certificates: a certificate authority made for one folder of secrets,
which signs the router's certificate (and with mutual TLS one per user), then its key is deleted.

Keys and certificates are made by the ``openssl`` command line, which writes the keys to files
itself (mode 0600): no secret is ever put on a command line.
"""

import secrets
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

from fleetmpc.errors import ConfigError
from fleetmpc.security.private_files import write_private

if TYPE_CHECKING:
    from fleetmpc.security.zenoh_security import ZenohSecurity

__all__ = ["CERTIFICATE_DAYS", "make_certificates"]

CERTIFICATE_DAYS = 30
"""Validity of the run-local CA and of the certificates it signs [days]."""

_NEW_KEY = ("-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes")
"""openssl req's options for a fresh unencrypted P-256 key (written by openssl, mode 0600)."""


def make_certificates(security: "ZenohSecurity", router_san: str) -> None:
    """The CA, the router's certificate and with mutual TLS one per user, signed in a private
    scratch folder inside the directory; the CA's key is deleted with it."""
    if shutil.which("openssl") is None:
        raise ConfigError("tls", "making the bus's certificates needs the openssl command line")
    scratch = Path(tempfile.mkdtemp(prefix=".zenoh-ca-", dir=security.directory))
    days = ("-days", str(CERTIFICATE_DAYS))
    try:
        ca_key, ca_cert = scratch / "ca.key", scratch / "ca.pem"
        subject = ("-subj", f"/CN=fleetmpc {security.fleet} run CA")
        ca_usage = ("-addext", "basicConstraints=critical,CA:TRUE")
        ca_usage += ("-addext", "keyUsage=critical,keyCertSign,cRLSign")
        outputs = ("-keyout", ca_key, "-out", ca_cert)
        _openssl("req", "-x509", "-new", *_NEW_KEY, *outputs, *days, *subject, *ca_usage)
        sans = [router_san] + (["DNS:localhost"] if router_san != "DNS:localhost" else [])
        leaves = [("router", "serverAuth", f"subjectAltName={','.join(sans)}\n")]
        if security.mutual_tls:
            leaves += [(user, "clientAuth", "") for user in security.users]
        copies = [(ca_cert, security.ca_certificate)]
        for name, usage, extra in leaves:
            extensions = scratch / f"{name}.ext"
            extensions.write_text(
                "basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\n"
                f"extendedKeyUsage={usage}\n{extra}"
            )
            key, request, cert = (scratch / f"{name}.{ext}" for ext in ("key", "csr", "pem"))
            _openssl(
                "req", "-new", *_NEW_KEY, "-keyout", key, "-out", request, "-subj", f"/CN={name}"
            )
            serial = ("-set_serial", f"0x{secrets.token_hex(16)}")
            signer = ("-CA", ca_cert, "-CAkey", ca_key, *serial, *days, "-extfile", extensions)
            _openssl("x509", "-req", "-in", request, *signer, "-out", cert)
            copies += [(cert, security.directory / f"zenoh-{name}.pem")]
            copies += [(key, security.directory / f"zenoh-{name}.key")]
        for source, dest in copies:
            write_private(dest, source.read_text(encoding="ascii"), field="directory")
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def _openssl(*args: str | Path) -> None:
    """Run the openssl command line (its arguments name files, never hold a secret)."""
    argv = ["openssl", *(str(a) for a in args)]
    result = subprocess.run(
        argv, stdin=subprocess.DEVNULL, capture_output=True, text=True, umask=0o077
    )
    if result.returncode != 0:
        raise ConfigError("tls", f"openssl {args[0]} failed: {result.stderr.strip()[-500:]}")
