"""How much of a run's held-out error is vertical streaks (issue 18).

  python heldout_streaks.py RUN_DIR FRAMES [--png OUT.png] [--bands N]   (numpy and scipy)

FRAMES is a comma list of frames the run wrote comparisons for (`comparison/frame_TTT.png`:
the held-out reference, 4 grey columns, the render; every `output_every` frames). For each,
inside the smoke (pixels of the reference more than 0.02 from its background, the median of
its 5-pixel border), prints the held-out PSNR over the whole image (as `eval` gives it, to
8-bit rounding) and two shares of the error's energy: what survives a running mean over 9
rows (error that stays the same down a column: vertical streaks) and over 9 columns (the
same along a row). Error without such structure keeps about 1/9 of its energy under either.
`--bands N` also prints the mean squared error in N equal bands of image rows, top first,
averaged over the frames: where in height the error sits (the source is in the lowest band
with smoke).

Why: every camera of the synthetic plume (and of ScalarFlow) sits at about the smoke's
height, so a horizontal slice of the smoke is seen from the same few directions in every
frame; detail the training views cannot place in depth shows in the held-out view as
vertical streaks where the smoke is a rising column. `--png` writes reference | error (grey
= none, white and black = +-0.03), one row per frame, 4x enlarged.

PNGs are decoded here (8-bit RGB or RGBA, not interlaced: what the project writes).
"""

import os
import struct
import sys
import zlib

import numpy as np
from scipy.ndimage import uniform_filter1d


def read_png(path, rgb=False):
    """An 8-bit, non-interlaced RGB(A) PNG as float greys in [0, 1], shape [H, W] (with
    `rgb`, its colours, shape [H, W, 3])."""
    data = open(path, "rb").read()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", f"{path}: not a PNG"
    pos, idat, header = 8, b"", None
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + length]
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat += body
        pos += 12 + length
    width, height, depth, colour, _, _, interlace = header
    channels = {2: 3, 6: 4}.get(colour)
    assert depth == 8 and channels and not interlace, f"{path}: unsupported PNG layout"
    raw = zlib.decompress(idat)
    stride = width * channels
    rows = np.zeros((height, stride), np.int32)
    previous = np.zeros(stride, np.int32)
    for y in range(height):
        line = raw[y * (stride + 1) : (y + 1) * (stride + 1)]
        kind, row = line[0], np.frombuffer(line[1:], np.uint8).astype(np.int32)
        out = np.zeros(stride, np.int32)
        for x in range(stride):
            left = out[x - channels] if x >= channels else 0
            up = previous[x]
            up_left = previous[x - channels] if x >= channels else 0
            if kind == 0:
                predicted = 0
            elif kind == 1:
                predicted = left
            elif kind == 2:
                predicted = up
            elif kind == 3:
                predicted = (left + up) // 2
            else:
                p = left + up - up_left
                pa, pb, pc = abs(p - left), abs(p - up), abs(p - up_left)
                predicted = left if pa <= pb and pa <= pc else (up if pb <= pc else up_left)
            out[x] = (row[x] + predicted) & 0xFF
        rows[y], previous = out, out
    pixels = rows.reshape(height, width, channels)[:, :, :3] / 255.0
    return pixels if rgb else pixels.mean(axis=2)


def write_png(path, grey):
    """Greys in [0, 1], shape [H, W], as an 8-bit greyscale PNG."""
    values = (np.clip(grey, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    raw = b"".join(b"\x00" + row.tobytes() for row in values)
    chunk = lambda kind, body: (
        struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))
    )
    header = struct.pack(">IIBBBBB", values.shape[1], values.shape[0], 8, 0, 0, 0, 0)
    with open(path, "wb") as out:
        out.write(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header))
        out.write(chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


def shares(error, smoke):
    """Energy shares of `error` inside `smoke` kept by 9-row and by 9-column running means."""
    total = (error[smoke] ** 2).sum()
    down = uniform_filter1d(error, 9, axis=0)
    along = uniform_filter1d(error, 9, axis=1)
    return (down[smoke] ** 2).sum() / total, (along[smoke] ** 2).sum() / total


def main(run, frames, png, bands):
    rows = []
    band_errors = np.zeros(bands)
    for t in frames:
        pair = read_png(os.path.join(run, "comparison", f"frame_{t:03d}.png"))
        width = (pair.shape[1] - 4) // 2
        reference, render = pair[:, :width], pair[:, width + 4 :]
        error = render - reference
        psnr = -10.0 * np.log10((error**2).mean())
        border = np.concatenate(
            [reference[:5].ravel(), reference[-5:].ravel(), reference[:, :5].ravel(),
             reference[:, -5:].ravel()]
        )
        smoke = np.abs(reference - np.median(border)) > 0.02
        vertical, horizontal = shares(error, smoke)
        for band, part in enumerate(np.array_split(error, bands, axis=0) if bands else []):
            band_errors[band] += (part**2).mean() / len(frames)
        print(
            f"frame {t:3d}: held-out PSNR {psnr:6.2f} dB; smoke {smoke.mean():.2f} of the "
            f"image; its error energy kept by a 9-row mean {vertical:.2f}, by a 9-column "
            f"mean {horizontal:.2f}"
        )
        lo, hi = reference.min(), reference.max()
        scaled = (reference - lo) / max(hi - lo, 1e-6)
        rows.append(np.concatenate([scaled, np.clip(0.5 + error / 0.06, 0.0, 1.0)], axis=1))
    if bands:
        print("mean squared error by band of rows, top first: "
              + " ".join(f"{e:.2e}" for e in band_errors))
    if png:
        picture = np.concatenate(rows, axis=0)
        write_png(png, np.repeat(np.repeat(picture, 4, axis=0), 4, axis=1))
        print(f"wrote {png}")


if __name__ == "__main__":
    args = sys.argv[1:]
    png = None
    if "--png" in args:
        i = args.index("--png")
        png = args[i + 1]
        del args[i : i + 2]
    bands = 0
    if "--bands" in args:
        i = args.index("--bands")
        bands = int(args[i + 1])
        del args[i : i + 2]
    if len(args) != 2:
        sys.exit(__doc__)
    main(args[0], [int(t) for t in args[1].split(",")], png, bands)
