"""safetensors files of float32 tensors, read and written by hand (NumPy only), for the Python
scripts beside this one. hac-nn's own files keep their metadata as one `hac_nn` string of
`key=value` pairs joined by `;` (layout in docs/CHECKPOINTS.md)."""
import json
import struct

import numpy as np


def write_safetensors(path, tensors, metadata):
    header, blobs, offset = {}, [], 0
    for name, array in tensors.items():
        data = np.ascontiguousarray(array, dtype="<f4").tobytes()
        header[name] = {"dtype": "F32", "shape": list(np.shape(array)),
                        "data_offsets": [offset, offset + len(data)]}
        blobs.append(data)
        offset += len(data)
    header["__metadata__"] = metadata
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)
    with open(path, "wb") as f:
        f.write(struct.pack("<Q", len(text)))
        f.write(text)
        for data in blobs:
            f.write(data)


def read_safetensors(path):
    with open(path, "rb") as f:
        raw = f.read()
    (n,) = struct.unpack("<Q", raw[:8])
    header = json.loads(raw[8:8 + n])
    metadata = header.pop("__metadata__", {})
    tensors = {}
    for name, info in header.items():
        assert info["dtype"] == "F32", (name, info["dtype"])
        start, end = info["data_offsets"]
        tensors[name] = np.frombuffer(raw[8 + n + start:8 + n + end], "<f4").reshape(info["shape"])
    return tensors, metadata


def hac_nn_metadata(metadata):
    """The `key=value` pairs of a hac-nn file's `hac_nn` metadata string, as a dict."""
    return dict(kv.split("=", 1) for kv in metadata["hac_nn"].split(";"))
