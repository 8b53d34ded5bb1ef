/* point_interpolation.cl - values of the irradiance points interpolated at surface points.
 *
 * Model (subsurface/interpolation.py): v(x) = sum_p w_p v_p / sum_p w_p over the points p
 * within CUT of x whose normals face the same way as x's (dot(n_p, n_x) >= MIN_DOT, so the
 * other side of a thin part is not mixed in), with w_p = A_p exp(-|x - p|^2 / (2 sigma^2)):
 * the Gaussian the gather reconstructs irradiance with (cl/bssrdf_gather.cl), normalised
 * (Shepard 1968) so that a constant is reproduced exactly.  Also returned: the weighted mean
 * normal and mean squared distance (a curvature estimate, subsurface/adaptive.py) and the
 * total weight sum_p w_p (0: no point in reach; times the normalised value, the gather's
 * own unnormalised reconstruction).
 *
 * The points are bucketed on the host in a uniform grid of cells no smaller than CUT, sorted
 * by cell (cell_start: the first point of each cell, one past the last cell at the end), so
 * the 27 cells around x's cell hold every point within CUT.
 */

__kernel void interpolate_points(__global const float4 *qpos,    /* xyz */
                                 __global const float4 *qnrm,    /* xyz unit normal */
                                 const int nq,
                                 __global const float4 *ppos,    /* xyz, area */
                                 __global const float4 *pnrm,    /* xyz unit normal */
                                 __global const float4 *pval,    /* 4 values */
                                 __global const int *cell_start, /* ncells + 1 */
                                 const int nx, const int ny, const int nz,
                                 const float4 lo, const float inv_cell,
                                 const float inv_two_s2, const float cut2,
                                 const float min_dot,
                                 __global float4 *out_val,       /* interpolated values */
                                 __global float4 *out_geo,       /* mean normal, mean d^2 */
                                 __global float *out_sum)        /* sum of w */
{
    const int i = get_global_id(0);
    if (i >= nq)
        return;
    const float3 x = qpos[i].xyz;
    const float3 n = qnrm[i].xyz;
    const int cx = clamp((int)floor((x.x - lo.x) * inv_cell), 0, nx - 1);
    const int cy = clamp((int)floor((x.y - lo.y) * inv_cell), 0, ny - 1);
    const int cz = clamp((int)floor((x.z - lo.z) * inv_cell), 0, nz - 1);
    float4 acc = (float4)(0.0f);
    float3 nacc = (float3)(0.0f);
    float wsum = 0.0f, d2sum = 0.0f;
    for (int z = max(cz - 1, 0); z <= min(cz + 1, nz - 1); ++z) {
        for (int y = max(cy - 1, 0); y <= min(cy + 1, ny - 1); ++y) {
            const int row = (z * ny + y) * nx;
            const int a = cell_start[row + max(cx - 1, 0)];
            const int b = cell_start[row + min(cx + 1, nx - 1) + 1];
            for (int j = a; j < b; ++j) {   /* the three cells along x are contiguous */
                const float4 p = ppos[j];
                const float3 d = p.xyz - x;
                const float r2 = dot(d, d);
                if (r2 > cut2)
                    continue;
                const float3 pn = pnrm[j].xyz;
                if (dot(pn, n) < min_dot)
                    continue;
                const float w = p.w * exp(-r2 * inv_two_s2);
                acc += w * pval[j];
                nacc += w * pn;
                wsum += w;
                d2sum += w * r2;
            }
        }
    }
    if (wsum > 0.0f) {
        const float inv = 1.0f / wsum;
        out_val[i] = acc * inv;
        out_geo[i] = (float4)(nacc * inv, d2sum * inv);
    } else {
        out_val[i] = (float4)(0.0f);
        out_geo[i] = (float4)(0.0f);
    }
    out_sum[i] = wsum;
}
