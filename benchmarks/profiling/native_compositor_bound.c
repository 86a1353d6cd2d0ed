/* What a native CPU kernel would buy the compositor: the carried compositor's per pair-pixel
 * math (raster/carried.py) as plain C loops over an 8x8 tile's pixels that the compiler
 * vectorises, with each tile's planes in L1. The forward: _evaluate, then _blend's transmittance,
 * weights and backward marks, and the alpha and colour sums of _pixel_sums. The backward:
 * backward_part as at fern step 1,250 (no depth, normal or median terms). Single-threaded, so
 * its nanoseconds per pair-pixel compare with fusion_profile.py's thread time per evaluated
 * pair-pixel of each loop. Evidence for the decision in the README ("What bounds it"), not part
 * of the package: the rasterizer stays JAX.
 *
 *   gcc -O3 -march=native -ffast-math -fopenmp-simd -o /tmp/ncb benchmarks/profiling/native_compositor_bound.c -lm && /tmp/ncb
 *
 * Prints one JSON object. Synthetic pairs at fern step 1,250's scale: 24M pair-pixels a pass.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#define TILE 8
#define P (TILE * TILE)
#define T_MIN 1e-4f

typedef struct { float pc[3], a[3], b[3], det, cx, cy, opacity, depth, color[3]; } Row;

static double now(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return t.tv_sec + 1e-9 * t.tv_nsec;
}

static float uniform(void) { return rand() / (float)RAND_MAX; }

/* alpha, hit depth and what the backward needs at one pixel (dx, dy) from the filter centre:
 * carried.py's _evaluate. */
typedef struct { float alpha, z, u, v, inv, rho, e, oe; int hit; } Eval;

static inline Eval evaluate(const Row *r, float dx, float dy, float near) {
    Eval o;
    float p0 = r->pc[0] + r->a[0] * dx + r->b[0] * dy;
    float p1 = r->pc[1] + r->a[1] * dx + r->b[1] * dy;
    float p2 = r->pc[2] + r->a[2] * dx + r->b[2] * dy;
    int ok = (fabsf(p0) < 1e6f * fabsf(p2)) & (fabsf(p1) < 1e6f * fabsf(p2));
    o.inv = 1.0f / (ok ? p2 : 1.0f);
    o.u = p0 * o.inv, o.v = p1 * o.inv;
    float rho3 = ok ? o.u * o.u + o.v * o.v : INFINITY;
    float rho2 = 2.0f * (dx * dx + dy * dy);
    o.hit = rho3 <= rho2;
    o.rho = o.hit ? rho3 : rho2;
    o.z = o.hit ? r->det * o.inv : r->depth;
    o.e = expf(-0.5f * o.rho);
    o.oe = r->opacity * o.e;
    int keep = (o.oe >= 1.0f / 255.0f) & (o.z >= near);
    o.alpha = keep ? fminf(0.99f, o.oe) : 0.0f;
    return o;
}

/* One tile's forward: walk its pairs front to back, every pixel evaluated for every pair (no
 * early exit: the JAX walk evaluates every pair-pixel of its chunks). Returns the live pairs. */
static int tile_forward(const Row *rows, const int *pair, int n, float x0, float y0, float near,
                        float out[4][P]) {
    float trans[P], acc[4][P] = {{0}};
    int live_pairs = 0;
    for (int p = 0; p < P; p++) trans[p] = 1.0f;
    for (int j = 0; j < n; j++) {
        const Row *r = &rows[pair[j]];
        float ox = x0 - r->cx, oy = y0 - r->cy;
        int live = 0;
#pragma omp simd reduction(|: live)
        for (int p = 0; p < P; p++) {
            Eval o = evaluate(r, ox + (p % TILE) + 0.5f, oy + (p / TILE) + 0.5f, near);
            float before = trans[p], after = before * (1.0f - o.alpha);
            float w = ((o.alpha > 0.0f) & (after >= T_MIN)) ? o.alpha * before : 0.0f;
            live |= (o.alpha > 0.0f) & (before >= T_MIN);
            trans[p] = after;
            acc[0][p] += w;
            acc[1][p] += w * r->color[0];
            acc[2][p] += w * r->color[1];
            acc[3][p] += w * r->color[2];
        }
        live_pairs += live;
    }
    for (int f = 0; f < 4; f++)
        for (int p = 0; p < P; p++) out[f][p] += acc[f][p];
    return live_pairs;
}

/* One tile's backward (carried.py's backward_part without depth, normal or median, as at fern
 * step 1,250): recompute the blend front to back, carry the prefix of w (g . f), and pull d alpha
 * back through the evaluation by hand into the pair's row gradient (14 geometric fields and 3
 * colour channels, scatter-added). g: the cotangents of alpha and rgb; total: the forward's sums. */
static void tile_backward(const Row *rows, const int *pair, int n, float x0, float y0, float near,
                          const float g[4][P], const float total[4][P], float (*d_rows)[17]) {
    float trans[P], prefix[P], g_dot_total[P];
    for (int p = 0; p < P; p++) {
        trans[p] = 1.0f, prefix[p] = 0.0f;
        g_dot_total[p] = g[0][p] * total[0][p] + g[1][p] * total[1][p] + g[2][p] * total[2][p] +
                         g[3][p] * total[3][p];
    }
    for (int j = 0; j < n; j++) {
        const Row *r = &rows[pair[j]];
        float ox = x0 - r->cx, oy = y0 - r->cy;
        /* Two loops over planes, sums after them: as one loop with int masks and 16 reductions,
         * gcc 12 kept it scalar (expf included) at 21 ns per pair-pixel. */
        float plane[16][P];
        float alpha[P], u[P], v[P], inv[P], rho[P], e[P], oe[P], hit[P];
#pragma omp simd
        for (int p = 0; p < P; p++) {
            Eval o = evaluate(r, ox + (p % TILE) + 0.5f, oy + (p / TILE) + 0.5f, near);
            alpha[p] = o.alpha, u[p] = o.u, v[p] = o.v, inv[p] = o.inv, rho[p] = o.rho, e[p] = o.e;
            oe[p] = o.oe, hit[p] = (float)o.hit;
        }
#pragma omp simd
        for (int p = 0; p < P; p++) {
            float xl = (p % TILE) + 0.5f, yl = (p / TILE) + 0.5f;
            float before = trans[p], one_minus = 1.0f - alpha[p], after = before * one_minus;
            float included = alpha[p] > 0.0f ? (after >= T_MIN ? 1.0f : 0.0f) : 0.0f;
            float w = included * alpha[p] * before;
            float h = g[0][p] + r->color[0] * g[1][p] + r->color[1] * g[2][p] + r->color[2] * g[3][p];
            prefix[p] += w * h;
            float rest = g_dot_total[p] - prefix[p];
            float d_alpha = included * (before * h * one_minus - rest) / one_minus;
            trans[p] = after;
            float unclamped = d_alpha != 0.0f ? (oe[p] < 0.99f ? 1.0f : 0.0f) : 0.0f;
            float g_rho = unclamped * -0.5f * oe[p] * d_alpha;
            float g_hit = hit[p] * g_rho, g_filter = (1.0f - hit[p]) * g_rho;
            float q[4] = {2.0f * g_hit * u[p] * inv[p], 2.0f * g_hit * v[p] * inv[p],
                          -2.0f * g_hit * rho[p] * inv[p], g_filter};
            for (int k = 0; k < 4; k++)
                plane[3 * k][p] = q[k], plane[3 * k + 1][p] = q[k] * xl, plane[3 * k + 2][p] = q[k] * yl;
            plane[12][p] = unclamped * e[p] * d_alpha;
            plane[13][p] = w * g[1][p], plane[14][p] = w * g[2][p], plane[15][p] = w * g[3][p];
        }
        float sum[16] = {0};
        for (int k = 0; k < 16; k++)
            for (int p = 0; p < P; p++) sum[k] += plane[k][p];
        float *d = d_rows[pair[j]], d_cx = 0.0f, d_cy = 0.0f;
        for (int q = 0; q < 3; q++) {  /* pc, a, b from the sums against [1, dx, dy] */
            const float *sq = sum + 3 * q;
            d[q] += sq[0], d[3 + q] += sq[1] + ox * sq[0], d[6 + q] += sq[2] + oy * sq[0];
            d_cx -= r->a[q] * sq[0], d_cy -= r->b[q] * sq[0];
        }
        d[9] += d_cx - 4.0f * (sum[10] + ox * sum[9]);   /* the filter branch's sums: 9, 10, 11 */
        d[10] += d_cy - 4.0f * (sum[11] + oy * sum[9]);
        d[11] += sum[12];                                 /* opacity */
        for (int c = 0; c < 3; c++) d[14 + c] += sum[13 + c];
    }
}

static int by_double(const void *a, const void *b) {
    double d = *(const double *)a - *(const double *)b;
    return (d > 0) - (d < 0);
}

int main(void) {
    const int tiles_x = 63, tiles = 63 * 47;  /* 504x378 in 8-px tiles */
    const int per_tile = 130, surfels = 67000, reps = 7;  /* 24M pair-pixels a pass */
    Row *rows = malloc(sizeof(Row) * surfels);
    int *pair = malloc(sizeof(int) * tiles * per_tile);
    srand(1);
    for (int i = 0; i < surfels; i++) {
        Row *r = &rows[i];
        /* A surfel seen near-frontally with a 2-6 px footprint: p = (dx / s, dy / s, 1) / 1. */
        float s = 2.0f + 4.0f * uniform(), depth = 1.0f + 4.0f * uniform();
        r->cx = 504.0f * uniform();
        r->cy = 378.0f * uniform();
        r->pc[0] = r->pc[1] = 0.0f, r->pc[2] = 1.0f;
        r->a[0] = 1.0f / s, r->a[1] = 0.1f * (uniform() - 0.5f) / s, r->a[2] = 0.0f;
        r->b[0] = 0.1f * (uniform() - 0.5f) / s, r->b[1] = 1.0f / s, r->b[2] = 0.0f;
        r->det = depth, r->depth = depth, r->opacity = 0.05f + 0.9f * uniform();
        for (int c = 0; c < 3; c++) r->color[c] = uniform();
    }
    /* Each tile's pairs: surfels centred in it or in one of its 8 neighbours, as binning would
     * list them (the order stands in for the depth sort). */
    int *bucket = malloc(sizeof(int) * surfels);
    for (int i = 0; i < surfels; i++)
        bucket[i] = (int)(rows[i].cy / TILE) * tiles_x + (int)(rows[i].cx / TILE);
    for (int t = 0; t < tiles; t++) {
        int tx = t % tiles_x, ty = t / tiles_x, j = 0;
        while (j < per_tile) {
            int i = rand() % surfels, bx = bucket[i] % tiles_x, by = bucket[i] / tiles_x;
            if (abs(bx - tx) <= 1 && abs(by - ty) <= 1) pair[t * per_tile + j++] = i;
        }
    }
    /* The forward's per-tile sums (the backward reads them) and cotangents like an L1 loss's. */
    float (*totals)[4][P] = calloc(tiles, sizeof *totals);
    static float g[4][P];
    for (int f = 0; f < 4; f++)
        for (int p = 0; p < P; p++) g[f][p] = f == 0 ? 0.0f : (uniform() < 0.5f ? -1e-6f : 1e-6f);
    float (*d_rows)[17] = calloc(surfels, sizeof *d_rows);
    double forward[16], backward[16];
    long live = 0;
    for (int rep = 0; rep < reps; rep++) {
        double t = now();
        live = 0;
        for (int k = 0; k < tiles; k++) {
            memset(totals[k], 0, sizeof totals[k]);
            live += tile_forward(rows, pair + k * per_tile, per_tile, TILE * (k % tiles_x),
                                 TILE * (k / tiles_x), 0.2f, totals[k]);
        }
        forward[rep] = now() - t;
        t = now();
        memset(d_rows, 0, surfels * sizeof *d_rows);
        for (int k = 0; k < tiles; k++)
            tile_backward(rows, pair + k * per_tile, per_tile, TILE * (k % tiles_x), TILE * (k / tiles_x),
                          0.2f, g, totals[k], d_rows);
        backward[rep] = now() - t;
    }
    qsort(forward, reps, sizeof(double), by_double);
    qsort(backward, reps, sizeof(double), by_double);
    double pair_pixels = (double)tiles * per_tile * P, checksum = 0.0;
    for (int i = 0; i < surfels; i++) checksum += fabsf(d_rows[i][0]) + fabsf(d_rows[i][11]);
    printf("{\"pair_pixels\": %.0f, \"forward_median_s\": %.5f, \"backward_median_s\": %.5f, "
           "\"forward_ns_per_pair_pixel\": %.3f, \"backward_ns_per_pair_pixel\": %.3f, "
           "\"live_pair_fraction\": %.3f, \"checksum\": [%.3f, %.6g]}\n",
           pair_pixels, forward[reps / 2], backward[reps / 2], 1e9 * forward[reps / 2] / pair_pixels,
           1e9 * backward[reps / 2] / pair_pixels, (double)live / ((double)tiles * per_tile),
           totals[0][0][0] + totals[7][1][7], checksum);
    return 0;
}
