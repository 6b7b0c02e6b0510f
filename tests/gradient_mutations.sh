#!/usr/bin/env bash
# Mutation check of the renderer's backward pass: each run drops one term of the gradient and
# rebuilds; both gradient test files (torch goldens, finite differences) must then fail.
# Slow (one rebuild per mutation, ~1 min each); run by hand after changing the backward:
#   bash tests/gradient_mutations.sh
set -u
backup=$(mktemp)
cd "$(git rev-parse --show-toplevel)"
run() {
  local file=$1 from=$2 to=$3 label=$4
  cp $file "$backup"
  python3 - "$file" "$from" "$to" <<'PY'
import sys
p, a, b = sys.argv[1:]
s = open(p).read()
assert s.count(a) == 1, f"pattern not unique: {a!r} ({s.count(a)})"
open(p, 'w').write(s.replace(a, b))
PY
  g=$(cargo test -p gausmoke-tests --test render_goldens 2>&1 | grep -c "test result: FAILED")
  f=$(cargo test -p gausmoke-tests --test render_gradcheck 2>&1 | grep -c "test result: FAILED")
  echo "$label: goldens_failed=$g fd_failed=$f"
  cp "$backup" $file
}
C=gausmoke-render/src/cpu.rs
M=gausmoke-render/src/math.rs
run $C "let mut grad_alpha = -grad_final_t * final_t / one_minus;" "let mut grad_alpha = 0.0;" "transmittance-output term of dL/dalpha"
run $C "(transmittance_before * splat.color[c] - behind[c] / one_minus)" "(transmittance_before * splat.color[c])" "occlusion-of-behind term of dL/dalpha"
run $C "g.sigma += grad_optical_depth * op.sample.integral;" "" "density gradient"
run $C "grad_background[c] += grad_color[c] * final_t;" "" "background gradient"
run $C "g.color[c] += grad_color[c] * transmittance_before * op.alpha;" "" "colour gradient"
run $M "let g_e = g_ln * (-s.dir_whitened[k] / s.dir_norm_sq - s.peak_depth * s.residual[k]);" "let g_e = g_ln * (-s.dir_whitened[k] / s.dir_norm_sq);" "transverse term of dlnI/de"
run $M "let g_e = g_ln * (-s.dir_whitened[k] / s.dir_norm_sq - s.peak_depth * s.residual[k]);" "let g_e = g_ln * (-s.peak_depth * s.residual[k]);" "beta term of dlnI/de"
run $M "grad_center[k] += g_ln * s.residual[k];" "" "dlnI/dm"
run $M "grad.log_scale[k] = -dot3(grad_whiten[k], whiten_row) - grad_center[k] * center_k;" "grad.log_scale[k] = -dot3(grad_whiten[k], whiten_row);" "centre part of log-scale gradient"
run $M "grad_axes[k][l] = (wt_g + grad_center[k] * ctx.offset[l]) * inv_s;" "grad_axes[k][l] = wt_g * inv_s;" "centre part of rotation gradient"
run $M "grad.quat = normalize_vjp(ctx.unit_quat, ctx.quat_norm, grad_unit);" "grad.quat = grad_unit;" "quaternion normalisation"
run $M "raw_density: grad_sigma * softplus_grad(g.raw_density)," "raw_density: grad_sigma," "softplus chain"
echo MUTATIONS DONE
