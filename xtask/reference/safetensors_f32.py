"""Writing float32 arrays as a safetensors file with numpy alone (the reference scripts that
must not need torch or the safetensors package import this)."""

import json
import struct

import numpy as np


def write_safetensors(path, tensors, metadata):
    """`tensors`: name -> array (stored as little-endian float32, C order); `metadata`:
    str -> str, kept in the header's `__metadata__`."""
    header = {"__metadata__": metadata}
    offset = 0
    blobs = []
    for name, array in tensors.items():
        array = np.ascontiguousarray(array, dtype="<f4")
        header[name] = {"dtype": "F32", "shape": list(array.shape),
                        "data_offsets": [offset, offset + array.nbytes]}
        offset += array.nbytes
        blobs.append(array.tobytes())
    text = json.dumps(header).encode()
    text += b" " * ((8 - len(text) % 8) % 8)
    with open(path, "wb") as f:
        f.write(struct.pack("<Q", len(text)))
        f.write(text)
        for blob in blobs:
            f.write(blob)
