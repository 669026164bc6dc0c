"""Content hashes of files: what decides whether a cached product (tables, OSL texture, fit) is current."""
import hashlib


def file_hash(path):
    """sha256 hex digest of the file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()
