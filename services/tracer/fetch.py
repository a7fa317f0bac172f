"""Chunks for a tracer without the chunk store (a LAN node): the manifest
comes with the server's welcome, and each chunk file is fetched by id when
first needed, checked against the manifest's SHA-256, and kept in a local
cache directory for the next render of the same store (same key).

A chunk is requested by its index only, never by path: the server maps the
index to its own file, so a tracer cannot name anything else on its disk.
"""
from __future__ import annotations

import hashlib
import os
import threading

import numpy as np

from dosppm_core.chunks.store import ChunkStore, StoreError


class FetchedStore:
    """A chunk provider (header, tree, chunk_memory, load) whose files are
    fetched through `request(chunk) -> [chunk_data messages]`."""

    def __init__(self, manifest: dict, cache_dir: str, request):
        os.makedirs(cache_dir, exist_ok=True)
        self.store = ChunkStore.from_manifest(cache_dir, manifest, check_files=False)
        self.header, self.tree = self.store.header, self.store.tree
        self.chunk_memory = self.store.chunk_memory
        self.key, self.manifest = self.store.key, manifest
        self.request = request
        self.fetched_bytes = 0
        # The chunk cache loads on a prefetch thread while the tracer's loop
        # reads its sockets: only the loop may touch them, so a prefetch of
        # a missing file fails and the chunk is fetched at activation.
        self._loop_thread = threading.get_ident()

    def load(self, k: int):
        try:
            return self.store.load(k)
        except StoreError:
            if threading.get_ident() != self._loop_thread:
                raise
        self._fetch(k)
        return self.store.load(k)

    def _fetch(self, k: int) -> None:
        entry = self.manifest["chunks"][k]
        data = np.zeros(int(entry["file_bytes"]), np.uint8)
        for part in self.request(k):
            if part.sha256 != entry["sha256"] or part.file_bytes != len(data):
                raise StoreError(f"chunk {k}: the server sent a different file than its manifest names")
            data[part.offset:part.offset + len(part.data)] = part.data
        if hashlib.sha256(data).hexdigest() != entry["sha256"]:
            raise StoreError(f"chunk {k}: fetched file fails its SHA-256 check")
        path = os.path.join(self.store.path, entry["file"])
        tmp = f"{path}.tmp-{os.getpid()}"
        with open(tmp, "wb") as f:
            f.write(data.tobytes())
        os.replace(tmp, path)
        self.fetched_bytes += len(data)
