"""The server's Ed25519 key file: created once with mode 600, refused when exposed. Both the
lab's setup (`server.core.lab`) and the signer of robot commands (`server.robots.signing`)
read it."""

from __future__ import annotations

import os
from pathlib import Path

from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey


def public_pem(key: Ed25519PrivateKey) -> str:
    """The public half as PEM text (what GET /api/server-key serves and agents pin)."""
    return (
        key.public_key()
        .public_bytes(serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo)
        .decode()
    )


def load_or_create_key(path: Path) -> Ed25519PrivateKey:
    """The private key at `path` (PEM, PKCS8), generated with mode 600 if the file is absent.

    ValueError when the file exists but is not an Ed25519 private key, or is readable by
    group or others (an exposed key must be replaced, not used).
    """
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        key = Ed25519PrivateKey.generate()
        path.parent.mkdir(parents=True, exist_ok=True)
        pem = key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
        # O_EXCL: two servers starting at once never overwrite each other's key
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "wb") as f:
            f.write(pem)
        return key
    if path.stat().st_mode & 0o077:
        raise ValueError(f"server key {path} is readable by others: chmod 600 it or delete it")
    loaded = serialization.load_pem_private_key(data, password=None)
    if not isinstance(loaded, Ed25519PrivateKey):
        raise ValueError(f"server key {path} is not an Ed25519 private key")
    return loaded
