// Geodesic distances along mesh edges from many sources: Dijkstra in Dinitz's bucket form.
//
// Distances are kept in buckets of width DELTA, no more than the shortest edge: every vertex in
// the lowest non-empty bucket then has its final distance (relaxing any edge from it adds at
// least DELTA, into a later bucket), so a bucket is settled in any order, with no heap. Each
// vertex is in at most one bucket, in a doubly linked list, so lowering its distance moves it in
// O(1). A ring of RING buckets (a power of two, more than longest edge / DELTA) covers every
// distance that can be pending at once. Every distance is the minimum of d[u] + w over the
// vertex's settled neighbours, as in the heap form, so the values are the same to the bit.
//
// One work-item per compute unit takes sources one after another from a shared counter; each
// has its own scratch lists (next, prev, bucket per vertex; the ring's heads).
#pragma OPENCL EXTENSION cl_khr_fp64 : enable

#define NONE    (-1)   // bucket of a vertex not reached yet
#define SETTLED (-2)   // bucket of a vertex whose distance is final

__kernel void geodesics(__global const int *indptr, __global const int *indices, __global const double *weights,
                        __global const int *sources, const int n_sources, const int n, const double inv_delta,
                        volatile __global int *next_source, __global double *dist,
                        __global int *next, __global int *prev, __global int *bucket, __global int *heads)
{
    const size_t item = get_global_id(0);
    next += item * (size_t)n;
    prev += item * (size_t)n;
    bucket += item * (size_t)n;
    heads += item * (size_t)RING;
    for (;;) {
        const int s = atomic_inc(next_source);
        if (s >= n_sources)
            return;
        __global double *d = dist + (size_t)s * n;
        for (int i = 0; i < n; ++i) {
            d[i] = INFINITY;
            bucket[i] = NONE;
        }
        for (int i = 0; i < RING; ++i)
            heads[i] = -1;
        const int source = sources[s];
        d[source] = 0.0;
        bucket[source] = 0;
        next[source] = prev[source] = -1;
        heads[0] = source;
        int queued = 1;
        for (long k = 0; queued > 0; ++k) {
            const int r = (int)(k & (RING - 1));
            int u;
            while ((u = heads[r]) >= 0) {
                const int after = next[u];
                heads[r] = after;
                if (after >= 0)
                    prev[after] = -1;
                bucket[u] = SETTLED;
                --queued;
                const double du = d[u];
                const int end = indptr[u + 1];
                for (int e = indptr[u]; e < end; ++e) {
                    const int v = indices[e];
                    const int bv = bucket[v];
                    if (bv == SETTLED)
                        continue;
                    const double dv = du + weights[e];
                    if (dv < d[v]) {
                        d[v] = dv;
                        if (bv >= 0) {  // out of its bucket
                            const int p = prev[v], q = next[v];
                            if (p >= 0) next[p] = q; else heads[bv] = q;
                            if (q >= 0) prev[q] = p;
                        } else {
                            ++queued;
                        }
                        const int b = (int)((long)(dv * inv_delta) & (RING - 1));
                        const int h = heads[b];
                        if (h >= 0)
                            prev[h] = v;
                        next[v] = h;
                        prev[v] = -1;
                        bucket[v] = b;
                        heads[b] = v;
                    }
                }
            }
        }
    }
}
