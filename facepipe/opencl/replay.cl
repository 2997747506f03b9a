/* facepipe replay kernels: one chunk of C frames of the whole per-frame evaluation.
 *
 * Layout. Work-items are (frame lane group, vertex): every work-item handles VW consecutive
 * frames of one vertex as one float vector. So everything that belongs to a vertex (its row of
 * B, its faces, its WPSD edges and RBF weights) is read once per work-item as a scalar and
 * broadcast, and everything that belongs to a frame (handle displacements, strain features,
 * head motion, positions) is contiguous along the frames: plain vector loads, no gathers, on a
 * CPU; on a GPU (VW = 1) a warp covers consecutive frames of one vertex, so the same accesses
 * are broadcasts and coalesced loads.
 *
 * Buffers (float32 unless noted; vertices in the engine's order, possibly permuted for locality):
 *   B      (Vp, H)      large-scale basis, rows padded with zeros to Vp
 *   U      (H, 3, C)    handle displacements of the chunk (head space), C = padded chunk
 *   rest   (Vp, 3)      rest positions
 *   large  (Vp, 3, C)   large-scale positions (head space), the hand-over between the kernels
 *   out    (C, V, 3)    final positions in the rest mesh's vertex order (out_index), world space,
 *                       from out_offset floats into the buffer
 *
 * Compile-time constants: VW (frames per work-item: 1, 2, 4, 8 or 16), H (handles), RV (vertices
 * per work-item in the B product), METHOD (0 none, 1 PSD, 2 WPSD, 3 local strain), P (basis poses, or
 * the local-strain model's training poses), K (WPSD
 * edges per vertex), F (feature edges), GATE (1: scale the details by the novelty gate's per-vertex
 * confidence Σ_k α_k site_{e_k}, site (F, C) from the host), PREFETCH (1 on a CPU: prefetch_fan).
 */

/* STAGES: both in production; the benchmark builds variants without one or both to time them */
#ifndef STAGES
#define STAGES 3
#endif
#ifndef PREFETCH
#define PREFETCH 0 /* 1 on CPU devices: __builtin_prefetch of the fans ahead (prefetch_fan) */
#endif
#define STAGE_FRAMES 1 /* normals and tangent frames of the large-scale surface */
#define STAGE_FINE 2   /* pose-space distances and the RBF sum */

#define METHOD_NONE 0
#define METHOD_PSD 1
#define METHOD_WPSD 2
#define METHOD_LOCAL_STRAIN 3

/* WPSD distances are summed term by term where r² < WPSD_CANCEL × (Σ α f² + Σ α b²): below it
 * the expanded sum's rounding (a few float ulps of those sums) would show in r = √r² */
#define WPSD_CANCEL 1e-3f

#if VW == 1
typedef float vfloat;
typedef int vint; /* what a comparison of two vfloat gives */
#else
#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)
typedef CAT(float, VW) vfloat;
typedef CAT(int, VW) vint;
#endif
/* Vector access through a cast rather than vloadN/vstoreN: PoCL calls those out of line, and
 * every call spills the accumulators to the stack (4× slower). Every such offset in these
 * kernels is a multiple of VW floats from a buffer's start (C is a multiple of VW), so the
 * vector alignment holds. */
#define VLOAD(p) (*(__global const vfloat *)(p))
#define VSTORE(x, p) (*(__global vfloat *)(p) = (x))

/* a·b + c written out: -cl-mad-enable lets the compiler contract it to one FMA instruction,
 * while PoCL calls the fma()/mad() builtins on vectors out of line (10× slower in a loop) */
#define FMA(a, b, c) ((a) * (b) + (c))
/* Likewise select() and fmax() are calls; the vector ?: is the same per-lane choice, inline. */
#define SELECT(a, b, c) ((c) ? (b) : (a))
#define MAX(a, b) ((a) > (b) ? (a) : (b))
/* sqrt() too is a call on PoCL; on x86 the instruction is reached through the compiler builtin.
 * Other devices (GPUs) use the standard sqrt(), which they inline. */
#if VW == 16 && defined(__AVX512F__)
#define VSQRT(x) __builtin_ia32_sqrtps512((x), 4) /* 4: the current rounding mode */
#elif VW == 8 && defined(__AVX__)
#define VSQRT(x) __builtin_ia32_sqrtps256(x)
#elif VW == 4 && defined(__SSE__)
#define VSQRT(x) __builtin_ia32_sqrtps(x)
#else
#define VSQRT(x) sqrt(x)
#endif
/* Helpers must be inlined: a call clobbers every vector register of the caller. */
#define FP_INLINE inline __attribute__((always_inline))

/* flags of detail(): which optional outputs to write */
#define WRITE_LARGE 1   /* out_large (C, V, 3): the large-scale positions, world space */
#define WRITE_FINAL_VC 2 /* final_vc (Vp, 3, C): final positions, head space (for final_normals) */

/* ------------------------------------------------------------------------------------------
 * Large scale: large = rest + B · U for C frames at once.
 *
 * A (V × H) · (H × 3C) product. Each work-item keeps RV vertices × 3 coordinates × VW frames
 * in registers and walks its RV rows of B once; the VW-frame slice of U (3 vectors per handle)
 * is shared by the RV rows. B streams from memory once per chunk (frame groups of the same
 * vertices run back to back, so the other groups find the rows in cache).
 * global size (C / VW, Vp / RV)
 */
__kernel void large_scale(__global const float *restrict B, __global const float *restrict U,
                          __global const float *restrict rest, __global float *restrict large,
                          const int C)
{
    const int c0 = get_global_id(0) * VW;
    const int v0 = get_global_id(1) * RV;
    vfloat acc[RV][3];
#pragma unroll
    for (int r = 0; r < RV; ++r) {
        acc[r][0] = (vfloat)(rest[(v0 + r) * 3 + 0]);
        acc[r][1] = (vfloat)(rest[(v0 + r) * 3 + 1]);
        acc[r][2] = (vfloat)(rest[(v0 + r) * 3 + 2]);
    }
    __global const float *b = B + (size_t)v0 * H;
    __global const float *u = U + c0;
    for (int h = 0; h < H; ++h) {
        const vfloat ux = VLOAD(u + (h * 3 + 0) * C);
        const vfloat uy = VLOAD(u + (h * 3 + 1) * C);
        const vfloat uz = VLOAD(u + (h * 3 + 2) * C);
#pragma unroll
        for (int r = 0; r < RV; ++r) {
            const vfloat w = (vfloat)(b[r * H + h]);
            acc[r][0] = FMA(w, ux, acc[r][0]);
            acc[r][1] = FMA(w, uy, acc[r][1]);
            acc[r][2] = FMA(w, uz, acc[r][2]);
        }
    }
#pragma unroll
    for (int r = 0; r < RV; ++r) {
        __global float *o = large + (size_t)(v0 + r) * 3 * C + c0;
        VSTORE(acc[r][0], o);
        VSTORE(acc[r][1], o + C);
        VSTORE(acc[r][2], o + 2 * C);
    }
}

/* The positions' row of the vertex a fan entry names (an entry j < 0 starts a fan at ~j). */
FP_INLINE __global const float *fan_row(__global const float *restrict pos, const int C, const int c0, const int j)
{
    return pos + (size_t)(j < 0 ? ~j : j) * 3 * C + c0;
}

/* Area-weighted vertex normal (not normalised) from the faces around v, walked as fans
 * (adjacency.vertex_fans): consecutive neighbours a, b of a fan span the face (v, a, b) in its
 * own winding, so cross(pa − pv, pb − pv) is that face's normal times twice its area. Each
 * neighbour is loaded and differenced once per fan, not once per face on either side of it; an
 * entry j < 0 starts a new fan at ~j. No atomics: every vertex sums its own faces. */
FP_INLINE void fan_normal(__global const float *restrict pos, const int C, const int c0,
                          __global const int *restrict fan_ptr, __global const int *restrict fan,
                          const int v, const vfloat px, const vfloat py, const vfloat pz,
                          vfloat *nx, vfloat *ny, vfloat *nz)
{
    vfloat sx = (vfloat)(0.0f), sy = (vfloat)(0.0f), sz = (vfloat)(0.0f);
    vfloat ax = (vfloat)(0.0f), ay = (vfloat)(0.0f), az = (vfloat)(0.0f);
    const int end = fan_ptr[v + 1];
    for (int i = fan_ptr[v]; i < end; ++i) {
        const int j = fan[i];
        __global const float *pb = fan_row(pos, C, c0, j);
        const vfloat bx = VLOAD(pb) - px, by = VLOAD(pb + C) - py, bz = VLOAD(pb + 2 * C) - pz;
        if (j >= 0) {
            sx = FMA(ay, bz, sx) - az * by;
            sy = FMA(az, bx, sy) - ax * bz;
            sz = FMA(ax, by, sz) - ay * bx;
        }
        ax = bx;
        ay = by;
        az = bz;
    }
    *nx = sx;
    *ny = sy;
    *nz = sz;
}

/* On a CPU (PREFETCH, set by the host): ask for the fan neighbours' positions of vertex w, the
 * one after this work-item's. A fan's loads depend on its list and stall on the cache lines of
 * the neighbours ahead (the next row of a mesh); requested one vertex early, they arrive while
 * this vertex is computed (at 530k vertices the fused kernel's time × 0.84, the median of seven
 * alternating pairs in one process; prefetching only each fan's furthest neighbour did no better). */
FP_INLINE void prefetch_fan(__global const float *restrict pos, const int C, const int c0,
                            __global const int *restrict fan_ptr, __global const int *restrict fan,
                            const int w, const int V)
{
#if PREFETCH
    if (w >= V)
        return;
    const int end = fan_ptr[w + 1];
    for (int i = fan_ptr[w]; i < end; ++i) {
        __global const float *p = fan_row(pos, C, c0, fan[i]);
        __builtin_prefetch(p);
        __builtin_prefetch(p + C);
        __builtin_prefetch(p + 2 * C);
    }
#endif
}

/* Unit vector with the reference's fallback where the length is (numerically) zero. */
FP_INLINE void normalize_or(vfloat *x, vfloat *y, vfloat *z, const float fx, const float fy, const float fz)
{
    const vfloat len = VSQRT(*x * *x + *y * *y + *z * *z);
    const vfloat inv = 1.0f / SELECT((vfloat)(1.0f), len, len > 1e-30f);
    *x = SELECT((vfloat)(fx), *x * inv, len > 1e-30f);
    *y = SELECT((vfloat)(fy), *y * inv, len > 1e-30f);
    *z = SELECT((vfloat)(fz), *z * inv, len > 1e-30f);
}

/* Store VW frames of one point (x, y, z) to out[(c * V + o) * 3 + 0..2]: per frame the three
 * coordinates together (one cache line touched once, not once per coordinate); lanes past
 * n_frames are padding and are dropped. */
FP_INLINE void store_point(__global float *restrict out, const vfloat x, const vfloat y, const vfloat z,
                           const int c0, const int n_frames, const int V, const int o)
{
    union {
        vfloat v;
        float s[VW];
    } lx, ly, lz;
    lx.v = x;
    ly.v = y;
    lz.v = z;
    __global float *q = out + ((size_t)c0 * V + o) * 3;
    const size_t stride = (size_t)V * 3;
    if (c0 + VW <= n_frames) {
#pragma unroll
        for (int j = 0; j < VW; ++j) {
            q[j * stride + 0] = lx.s[j];
            q[j * stride + 1] = ly.s[j];
            q[j * stride + 2] = lz.s[j];
        }
    } else {
        for (int j = 0; j < VW && c0 + j < n_frames; ++j) {
            q[j * stride + 0] = lx.s[j];
            q[j * stride + 1] = ly.s[j];
            q[j * stride + 2] = lz.s[j];
        }
    }
}

/* world = R · p + t with the per-frame head motion rigid (12, C): R row-major, then t. */
FP_INLINE void to_world(__global const float *restrict rigid, const int C, const int c0, vfloat *x, vfloat *y,
                     vfloat *z, const int translate)
{
    __global const float *m = rigid + c0;
    const vfloat X = *x, Y = *y, Z = *z;
    *x = VLOAD(m + 0 * C) * X + VLOAD(m + 1 * C) * Y + VLOAD(m + 2 * C) * Z;
    *y = VLOAD(m + 3 * C) * X + VLOAD(m + 4 * C) * Y + VLOAD(m + 5 * C) * Z;
    *z = VLOAD(m + 6 * C) * X + VLOAD(m + 7 * C) * Y + VLOAD(m + 8 * C) * Z;
    if (translate) {
        *x += VLOAD(m + 9 * C);
        *y += VLOAD(m + 10 * C);
        *z += VLOAD(m + 11 * C);
    }
}

/* ------------------------------------------------------------------------------------------
 * Frames, fine scale and output: per vertex and VW frames,
 *   n = normalised Σ face normals, t = neighbour edge projected into the tangent plane, b = n × t
 *   d = c_v + Σ_p w_{v,p} φ(r_{v,p})   (φ(r) = r)
 *       WPSD: r²_{v,p} = Σ_k α_{v,k} (f_{e_k} − f_{p,e_k})²   (α sparse, ≤ K edges, zeros last),
 *             expanded (see below)
 *       PSD:  r_p = |f − f_p| per frame, from the host (psd_r (P, C))
 *   final = large + t d_0 + b d_1 + n d_2, then the head motion, stored as (C, V, 3).
 * global size (C / VW, V)
 */
__kernel void detail(__global const float *restrict large, const int C, const int n_frames, const int V,
                     __global const int *restrict ring_ptr, __global const int2 *restrict ring,
                     __global const int *restrict fan_ptr, __global const int *restrict fan,
                     __global const int *restrict neighbor,
                     __global const int *restrict edge_count, __global const int *restrict edge_index,
                     __global const float *restrict edge_weight, __global const float *restrict basis,
                     __global const float *restrict features, __global const float *restrict psd_r,
                     __global const float *restrict site,
                     __global const float *restrict rbf_weights, __global const float *restrict rbf_const,
                     __global const float *restrict rigid, __global const int *restrict out_index,
                     __global float *restrict out, __global float *restrict out_large,
                     __global float *restrict final_vc, const int flags,
                     __global const float *restrict strain_coeff, __global const float *restrict strain_const,
                     __global const float *restrict strain_samples, const float strain_inv,
                     const int out_offset, __global const float *restrict wpsd_const)
{
    const int c0 = get_global_id(0) * VW;
    const int v = get_global_id(1);
    if (v >= V)
        return;
    /* the final positions start out_offset floats into out: a host buffer laid out for the
     * file the positions go to (direct writes start on a disk block, the data need not) */
    out += out_offset;
    __global const float *p = large + (size_t)v * 3 * C + c0;
    const vfloat px = VLOAD(p), py = VLOAD(p + C), pz = VLOAD(p + 2 * C);
    vfloat fx = px, fy = py, fz = pz;

#if METHOD != METHOD_NONE
#if STAGES & STAGE_FRAMES
    /* ---- local frame of the large-scale surface */
    vfloat nx, ny, nz;
    prefetch_fan(large, C, c0, fan_ptr, fan, v + 1, V);
    fan_normal(large, C, c0, fan_ptr, fan, v, px, py, pz, &nx, &ny, &nz);
    normalize_or(&nx, &ny, &nz, 0.0f, 0.0f, 1.0f);
    __global const float *q = large + (size_t)neighbor[v] * 3 * C + c0;
    const vfloat ex = VLOAD(q) - px, ey = VLOAD(q + C) - py, ez = VLOAD(q + 2 * C) - pz;
    const vfloat en = ex * nx + ey * ny + ez * nz;
    vfloat tx = ex - en * nx, ty = ey - en * ny, tz = ez - en * nz;
    /* an edge (anti)parallel to the normal has no tangent part: any perpendicular will do,
     * n × x̂, or n × ŷ when n is along x̂ (as the reference). The reference's length tests are
     * made on squared lengths: the same tests without three square roots, among the slowest
     * vector instructions (the fused kernel × 0.85–0.92 at 530k vertices, medians of seven
     * in-process pairs). */
    const vfloat tlen2 = tx * tx + ty * ty + tz * tz;
    const vfloat elen2 = ex * ex + ey * ey + ez * ez;
    const vint has_alt = nz * nz + ny * ny >= 1e-12f;           /* |(n_y, n_z)| ≥ 1e-6 */
    const vfloat ax = SELECT(-nz, (vfloat)(0.0f), has_alt);
    const vfloat ay = SELECT((vfloat)(0.0f), nz, has_alt);
    const vfloat az = SELECT(nx, -ny, has_alt);
    const vint keep = tlen2 > 1e-12f * elen2;                   /* |t| > 1e-6 |e| */
    tx = SELECT(ax, tx, keep);
    ty = SELECT(ay, ty, keep);
    tz = SELECT(az, tz, keep);
    normalize_or(&tx, &ty, &tz, 1.0f, 0.0f, 0.0f);
    const vfloat bx = ny * tz - nz * ty, by = nz * tx - nx * tz, bz = nx * ty - ny * tx;
#else /* benchmark variant: fixed frames */
    const vfloat tx = 1.0f, ty = 0.0f, tz = 0.0f, bx = 0.0f, by = 1.0f, bz = 0.0f, nx = 0.0f, ny = 0.0f, nz = 1.0f;
#endif

#if (STAGES & STAGE_FINE) && METHOD == METHOD_LOCAL_STRAIN
    /* ---- local strain of the large-scale surface at v (core.local_strain.ring_strain_coefficients):
     * s_k = const_k + Σ_ring coeff_k · (a·a, a·b, b·b), a and b the ring face's edges from v */
    vfloat s0 = (vfloat)(strain_const[v * 3 + 0]);
    vfloat s1 = (vfloat)(strain_const[v * 3 + 1]);
    vfloat s2 = (vfloat)(strain_const[v * 3 + 2]);
    const int ring_end = ring_ptr[v + 1];
    for (int i = ring_ptr[v]; i < ring_end; ++i) {
        const int2 ab = ring[i];
        __global const float *pa = large + (size_t)ab.x * 3 * C + c0;
        __global const float *pb = large + (size_t)ab.y * 3 * C + c0;
        const vfloat ax = VLOAD(pa) - px, ay = VLOAD(pa + C) - py, az = VLOAD(pa + 2 * C) - pz;
        const vfloat bx = VLOAD(pb) - px, by = VLOAD(pb + C) - py, bz = VLOAD(pb + 2 * C) - pz;
        const vfloat gaa = ax * ax + ay * ay + az * az;
        const vfloat gab = ax * bx + ay * by + az * bz;
        const vfloat gbb = bx * bx + by * by + bz * bz;
        __global const float *c = strain_coeff + (size_t)i * 9;
        s0 += c[0] * gaa + c[1] * gab + c[2] * gbb;
        s1 += c[3] * gaa + c[4] * gab + c[5] * gbb;
        s2 += c[6] * gaa + c[7] * gab + c[8] * gbb;
    }
    /* ---- Gaussian kernel regression over the training poses' strains at v (core.strain_details) */
    __global const float *w = rbf_weights + (size_t)v * P * 3;
    __global const float *sm = strain_samples + (size_t)v * P * 3;
    vfloat d0 = (vfloat)(0.0f), d1 = (vfloat)(0.0f), d2 = (vfloat)(0.0f);
    for (int i = 0; i < P; ++i) {
        const vfloat x = s0 - sm[i * 3 + 0], y = s1 - sm[i * 3 + 1], z = s2 - sm[i * 3 + 2];
        /* native_exp: the library exp is an out-of-line call per vector on PoCL (as sqrt), and
         * the kernel needs no more than float accuracy of a factor in [0, 1] */
        const vfloat k = native_exp(strain_inv * (x * x + y * y + z * z));
        d0 = FMA((vfloat)(w[i * 3 + 0]), k, d0);
        d1 = FMA((vfloat)(w[i * 3 + 1]), k, d1);
        d2 = FMA((vfloat)(w[i * 3 + 2]), k, d2);
    }
#elif STAGES & STAGE_FINE
    /* ---- pose-space distances (and the novelty gate, over the same α)
     * WPSD expands the square: r²_p = Σ_k α_k f_k² − 2 Σ_k α_k b_pk f_k + Σ_k α_k b_pk², the last
     * sum a per-vertex constant (wpsd_const), the host's basis already −2 b: one FMA per edge and
     * pose instead of a difference, a square and an FMA. The expansion cancels where a frame is
     * close to a basis pose (r² small against the sums); there, and only there, the distances are
     * summed again term by term, so φ(r) = r keeps float accuracy at and near the poses. */
    vfloat r[P];
#if METHOD == METHOD_WPSD
    __global const float *bsq = wpsd_const + (size_t)v * P;
    vfloat norm2 = (vfloat)(0.0f);
#pragma unroll
    for (int i = 0; i < P; ++i)
        r[i] = (vfloat)(bsq[i]);
#else
#pragma unroll
    for (int i = 0; i < P; ++i)
        r[i] = VLOAD(psd_r + i * C + c0);
#endif
#if METHOD == METHOD_WPSD || GATE
    vfloat confidence = (vfloat)(0.0f);
    const int count = edge_count[v];
    __global const int *ei = edge_index + (size_t)v * K;
    __global const float *ew = edge_weight + (size_t)v * K;
    for (int k = 0; k < count; ++k) {
        const int e = ei[k];
        const float a = ew[k];
#if METHOD == METHOD_WPSD
        const vfloat f = VLOAD(features + e * C + c0);
        const vfloat af = a * f;
        norm2 = FMA(af, f, norm2);
#pragma unroll
        for (int i = 0; i < P; ++i)
            r[i] = FMA(af, (vfloat)(basis[i * F + e]), r[i]);
#endif
#if GATE
        confidence = FMA((vfloat)(a), VLOAD(site + e * C + c0), confidence);
#endif
    }
#endif
#if METHOD == METHOD_WPSD
    vint near = (vint)(0);
#pragma unroll
    for (int i = 0; i < P; ++i) {
        r[i] += norm2;
        near |= r[i] < WPSD_CANCEL * (norm2 + bsq[i]);
    }
    union {
        vint v;
        int s[VW];
    } lanes;
    lanes.v = near;
    int any_near = 0;
#pragma unroll
    for (int j = 0; j < VW; ++j)
        any_near |= lanes.s[j];
    if (any_near) {
#pragma unroll
        for (int i = 0; i < P; ++i)
            r[i] = (vfloat)(0.0f);
        for (int k = 0; k < count; ++k) {
            const int e = ei[k];
            const float a = ew[k];
            const vfloat f = VLOAD(features + e * C + c0);
#pragma unroll
            for (int i = 0; i < P; ++i) {
                const vfloat d = f + 0.5f * basis[i * F + e]; /* f − b, exactly as stored: −2b / −2 */
                r[i] = FMA((vfloat)(a), d * d, r[i]);
            }
        }
    }
#pragma unroll
    for (int i = 0; i < P; ++i)
        r[i] = VSQRT(MAX(r[i], (vfloat)(0.0f)));
#endif

    /* ---- detail in the local frame, to world */
    __global const float *w = rbf_weights + (size_t)v * P * 3;
    vfloat d0 = (vfloat)(rbf_const[v * 3 + 0]);
    vfloat d1 = (vfloat)(rbf_const[v * 3 + 1]);
    vfloat d2 = (vfloat)(rbf_const[v * 3 + 2]);
#pragma unroll
    for (int i = 0; i < P; ++i) {
        d0 = FMA((vfloat)(w[i * 3 + 0]), r[i], d0);
        d1 = FMA((vfloat)(w[i * 3 + 1]), r[i], d1);
        d2 = FMA((vfloat)(w[i * 3 + 2]), r[i], d2);
    }
#if GATE
    /* details fade out where the strain is unlike the examples' (psd.NoveltyGate) */
    d0 *= confidence;
    d1 *= confidence;
    d2 *= confidence;
#endif
#else /* benchmark variant: the constant term only */
    const vfloat d0 = rbf_const[v * 3 + 0], d1 = rbf_const[v * 3 + 1], d2 = rbf_const[v * 3 + 2];
#endif
    fx += tx * d0 + bx * d1 + nx * d2;
    fy += ty * d0 + by * d1 + ny * d2;
    fz += tz * d0 + bz * d1 + nz * d2;
#endif

    if (flags & WRITE_FINAL_VC) {
        __global float *o = final_vc + (size_t)v * 3 * C + c0;
        VSTORE(fx, o);
        VSTORE(fy, o + C);
        VSTORE(fz, o + 2 * C);
    }
    const int o = out_index[v];
    to_world(rigid, C, c0, &fx, &fy, &fz, 1);
    store_point(out, fx, fy, fz, c0, n_frames, V, o);
    if (flags & WRITE_LARGE) {
        vfloat lx = px, ly = py, lz = pz;
        to_world(rigid, C, c0, &lx, &ly, &lz, 1);
        store_point(out_large, lx, ly, lz, c0, n_frames, V, o);
    }
}

/* ------------------------------------------------------------------------------------------
 * Unit normals of the final surface (for export), rotated with the head: (C, V, 3).
 * global size (C / VW, V); reads final_vc written by detail() with WRITE_FINAL_VC.
 */
__kernel void final_normals(__global const float *restrict final_vc, const int C, const int n_frames,
                            const int V, __global const int *restrict fan_ptr,
                            __global const int *restrict fan, __global const float *restrict rigid,
                            __global const int *restrict out_index, __global float *restrict normals)
{
    const int c0 = get_global_id(0) * VW;
    const int v = get_global_id(1);
    if (v >= V)
        return;
    __global const float *p = final_vc + (size_t)v * 3 * C + c0;
    vfloat nx, ny, nz;
    prefetch_fan(final_vc, C, c0, fan_ptr, fan, v + 1, V);
    fan_normal(final_vc, C, c0, fan_ptr, fan, v, VLOAD(p), VLOAD(p + C), VLOAD(p + 2 * C), &nx, &ny, &nz);
    normalize_or(&nx, &ny, &nz, 0.0f, 0.0f, 1.0f);
    to_world(rigid, C, c0, &nx, &ny, &nz, 0);
    const int o = out_index[v];
    store_point(normals, nx, ny, nz, c0, n_frames, V, o);
}
