"""How far a synthetic scene's true velocity lies from the fields the exact projection can
return, for open faces of each flow (issue 18).

  python truth_projection.py DATA_DIR FRAMES [--open y+] [--flows 0,0.5,1]
                                                        (needs numpy and scipy)

FRAMES is a comma list. The projection is rebuilt here from its definition, independently
of the Rust code: collocated cells, face velocity the mean of the two cells beside it, zero
on a solid box face and `flow` times the inner cell's on an open one (`open_face_flow`),
`P u = u - D^T (D D^T)^+ D u` by conjugate gradients in f64. Flow 0 makes the open faces
solid; 0.5 is the top of the synthetic generator, whose divergence reads zero velocity above
its open top. For each flow and frame, inside the true smoke (density above 1% of its
maximum) prints `|P u - u| / |u|` (the velocity error a run would keep if it found the truth's
projection exactly, in the same measure as the runs' `velocity_relative_error`), the same in
the top eighth of the box, and `|D u| / |u|` over the whole box.
"""

import argparse

import numpy as np
import scipy.sparse as sparse
import scipy.sparse.linalg as sparse_linalg

from scene_truth import read_truth


def divergence(n, open_faces, flow):
    """`D` (cells x 3 cells) on an n^3 grid of unit cells, x slowest, velocity [cells, 3]."""
    index = np.arange(n ** 3).reshape(n, n, n)
    rows, cols, vals = [], [], []
    for axis in range(3):
        low = np.take(index, np.arange(n - 1), axis=axis).ravel()
        high = np.take(index, np.arange(1, n), axis=axis).ravel()
        # The interior face between `low` and `high`: +flux for `low`, -flux for `high`.
        for cell, sign in ((low, 0.5), (high, -0.5)):
            for member in (low, high):
                rows.append(cell)
                cols.append(3 * member + axis)
                vals.append(np.full(cell.size, sign))
        for side, name in ((n - 1, "+"), (0, "-")):
            if f"{'xyz'[axis]}{name}" not in open_faces or flow == 0:
                continue
            cell = np.take(index, side, axis=axis).ravel()
            rows.append(cell)
            cols.append(3 * cell + axis)
            vals.append(np.full(cell.size, flow if name == "+" else -flow))
    return sparse.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(n ** 3, 3 * n ** 3),
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data")
    parser.add_argument("frames")
    parser.add_argument("--open", default="y+", help="comma list of open faces")
    parser.add_argument("--flows", default="0,0.5,1")
    args = parser.parse_args()
    frames = [int(t) for t in args.frames.split(",")]
    open_faces = args.open.split(",")
    truths = {t: read_truth(args.data, t) for t in frames}
    n = next(iter(truths.values()))[0].shape[0]
    for flow in (float(f) for f in args.flows.split(",")):
        d = divergence(n, open_faces, flow)
        normal = (d @ d.T).tocsr()
        for t, (density, velocity) in truths.items():
            u = velocity.reshape(-1)
            rhs = d @ u
            pressure, info = sparse_linalg.cg(normal, rhs, rtol=1e-10, maxiter=10000)
            if info != 0:
                raise SystemExit(f"flow {flow}, frame {t}: CG did not converge ({info})")
            change = (d.T @ pressure).reshape(velocity.shape)
            smoke = density > 0.01 * density.max()
            top = smoke.copy()
            top[:, : 7 * n // 8, :] = False

            def relative(mask):
                if mask.sum() == 0:
                    return "-"
                return f"{np.sqrt((change[mask] ** 2).sum() / (velocity[mask] ** 2).sum()):.3f}"

            print(
                f"flow {flow:g} frame {t}: |Pu - u|/|u| in the smoke {relative(smoke)}, "
                f"top eighth {relative(top)}; "
                f"|Du|/|u| {np.linalg.norm(rhs) / np.linalg.norm(u):.3f}"
            )


if __name__ == "__main__":
    main()
