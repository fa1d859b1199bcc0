/* Drop volumes of a small convex polytope, every plane at once (see polycc_caps.h).
 *
 * Hand-written because the half-plane reduction asks for them about 100,000 times on a 6M-splat build,
 * for polytopes of 5-128 planes: qhull (scipy) spends 0.3-0.6 ms a call on setup alone and numpy's
 * enumeration tens of array calls. The method is the numpy reference's
 * (polycc.geometry.halfplanes.drop_volumes and bounded_without), tested against it and against qhull:
 *
 * Caps. Every triple of planes meets in a point p (|det| > 1e-12 on unit normals). If p violates no plane
 * it is a vertex of P; if it violates only plane j, a vertex of the cap C_j = (P without j) minus P. The
 * faces of C_j lie on the other planes l: its vertices beyond j on l, and P's vertices on both j and l.
 * Its volume is the sum over faces of area x height / 3 from an apex on plane j (the mean of P's vertices
 * there), each area by the shoelace formula in angular order around the face's mean.
 *
 * Boundedness. gamma = min_{|w|=1} max_l u_l . w (u_l the unit normals) is 1 / max |x| over the vertices
 * of Q = {x : u_l . x <= 1}, the polar of the normals' hull (Q is bounded iff gamma > 0). Cut by the box
 * |x_i| <= 2 / g, Q's vertices all lie within 1 / g iff gamma > g: if Q reaches past that ball, the cut
 * polytope has a point, so a vertex, past it too. As in the reference, a subset S of the normals (the one
 * closest to each axis direction) bounded with twice the margin certifies every row outside S (a superset's
 * hull contains S's), a second such S' the rows of S, and the rows left get the full test without them.
 */
#include "polycc_caps.h"

#include <math.h>
#include <stdlib.h>

#define TOL_REL 1e-9    /* on / beyond a plane within 1e-9 x max(1, |d|max) (the reference's tolerance) */
#define DET_MIN 1e-12   /* triples of unit normals closer to coplanar than this meet nowhere useful */
#define GAMMA_BAND 1e-7 /* gamma within this relative distance of the margin: too close to call */
#define MIN_PLANES 4
#define MAXP POLYCC_CAPS_MAX_PLANES

typedef unsigned __int128 mask; /* one bit per plane (gcc and clang on 64-bit targets) */

typedef struct {
    double x, y, z;
} v3;

typedef struct {
    v3 p;
    int vj;      /* the one plane p violates, or -1: p is a vertex of P */
    mask on;     /* the planes p lies on */
} vertex;

typedef struct {
    int key; /* face j * m + l: the face of cap C_j on plane l */
    int idx; /* its vertex */
} entry;

typedef struct {
    double ang, x, y;
} corner;

static v3 cross(v3 a, v3 b) {
    v3 r;
    r.x = a.y * b.z - a.z * b.y;
    r.y = a.z * b.x - a.x * b.z;
    r.z = a.x * b.y - a.y * b.x;
    return r;
}

static double dot(v3 a, v3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }

static double maxabs(v3 a) { return fmax(fabs(a.x), fmax(fabs(a.y), fabs(a.z))); }

/* The point where a . p = ea, b . p = eb and c . p = ec (the reference's arithmetic); 0 if degenerate. */
static int meet(v3 a, v3 b, v3 c, double ea, double eb, double ec, v3 *p) {
    v3 bc = cross(b, c), ca = cross(c, a), ab = cross(a, b);
    double det = dot(a, bc);
    if (!(fabs(det) > DET_MIN)) return 0;
    p->x = (ea * bc.x + eb * ca.x + ec * ab.x) / det;
    p->y = (ea * bc.y + eb * ca.y + ec * ab.y) / det;
    p->z = (ea * bc.z + eb * ca.z + ec * ab.z) / det;
    return 1;
}

/* 1 if gamma > g, 0 if not, -1 if too close to call, from far2 = max |x|^2 over the polar's vertices. */
static int8_t classify(double far2, double g) {
    double far = sqrt(far2), reach = 1.0 / g;
    if (far < reach * (1.0 - GAMMA_BAND)) return 1;
    if (far > reach * (1.0 + GAMMA_BAND)) return 0;
    return -1;
}

/* The vertices of {x : u_r . x <= 1 for the k rows r = rows[i]} cut by the box |x_i| <= 2 / g: *all = the largest
 * |x|^2 among them; if without is not NULL, without[i] = the same with row rows[i] left out (the vertices of the
 * smaller polytope are the points of triples without that row that violate no other row, or only that one). */
static void polar_far(const v3 *u, const int *rows, int k, double g, double *all, double *without) {
    v3 a[MAXP + 6];
    double e[MAXP + 6], box = 2.0 / g;
    int K = k + 6, i, j, l, r;
    *all = 0.0;
    for (i = 0; i < k; i++) {
        a[i] = u[rows[i]];
        e[i] = 1.0;
        if (without) without[i] = 0.0;
    }
    for (i = 0; i < 6; i++) {
        v3 ax = {0.0, 0.0, 0.0};
        double s = (i & 1) ? -1.0 : 1.0;
        if (i / 2 == 0) ax.x = s;
        if (i / 2 == 1) ax.y = s;
        if (i / 2 == 2) ax.z = s;
        a[k + i] = ax;
        e[k + i] = box;
    }
    for (i = 0; i < K; i++)
        for (j = i + 1; j < K; j++)
            for (l = j + 1; l < K; l++) {
                v3 p;
                double tol, q;
                int nv = 0, vr = -1;
                if (!meet(a[i], a[j], a[l], e[i], e[j], e[l], &p)) continue;
                tol = TOL_REL * fmax(1.0, maxabs(p));
                for (r = 0; r < K && nv <= (without ? 1 : 0); r++) {
                    if (r == i || r == j || r == l) continue;
                    if (dot(a[r], p) - e[r] > tol) {
                        vr = r;
                        nv++;
                    }
                }
                if (nv > 1) continue;
                q = dot(p, p);
                if (nv == 0) {
                    if (q > *all) *all = q;
                    if (without)
                        for (r = 0; r < k; r++)
                            if (r != i && r != j && r != l && q > without[r]) without[r] = q;
                } else if (without && vr < k && q > without[vr]) {
                    without[vr] = q; /* beyond a box face it is no vertex of any of them */
                }
            }
}

/* The reference's bounded_without on unit normals: two certificate subsets, then the polar of every row left. */
static void bounded_states(const v3 *u, int m, double g, int8_t *state) {
    static const v3 axes[6] = {{1.0, 0.0, 0.0}, {0.0, 1.0, 0.0}, {0.0, 0.0, 1.0},
                               {-1.0, 0.0, 0.0}, {0.0, -1.0, 0.0}, {0.0, 0.0, -1.0}};
    int freev[MAXP], rows[MAXP], cert[6], ncert = 0, certs = 0, round, i, j;
    double all, without[MAXP];
    for (j = 0; j < m; j++) state[j] = 0;
    if (m <= MIN_PLANES) return;
    for (j = 0; j < m; j++) freev[j] = 1;
    for (round = 0; round < 2; round++) {
        int s[6], ns = 0, nfree = 0, ax;
        for (j = 0; j < m; j++) nfree += freev[j];
        if (nfree < MIN_PLANES) break;
        for (ax = 0; ax < 6; ax++) {
            double best = -INFINITY;
            int arg = -1, dup = 0;
            for (j = 0; j < m; j++) {
                double sc;
                if (!freev[j]) continue;
                sc = dot(axes[ax], u[j]);
                if (arg < 0 || sc > best) {
                    best = sc;
                    arg = j;
                }
            }
            for (i = 0; i < ns; i++) dup |= s[i] == arg;
            if (!dup) s[ns++] = arg;
        }
        if (ns < MIN_PLANES) break;
        polar_far(u, s, ns, 2.0 * g, &all, NULL);
        if (classify(all, 2.0 * g) != 1) break;
        if (certs == 0) {
            for (i = 0; i < ns; i++) cert[i] = s[i];
            ncert = ns;
        }
        for (i = 0; i < ns; i++) freev[s[i]] = 0;
        certs++;
    }
    if (certs == 2) {
        for (j = 0; j < m; j++) state[j] = 1;
        return;
    }
    for (j = 0; j < m; j++) rows[j] = j;
    polar_far(u, rows, m, g, &all, without); /* every row at once: the cost of one more enumeration */
    for (j = 0; j < m; j++) state[j] = certs ? 1 : classify(without[j], g);
    for (i = 0; i < ncert; i++) state[cert[i]] = classify(without[cert[i]], g);
}

/* u[l] = the unit normal of row l of h (stride doubles a row, the normal first), e[l] = the row's 4th value over
 * the normal's length if e is not NULL; 0, or -1 if m is out of range, the margin not positive or a normal zero. */
static int unit_rows(const double *h, int stride, int m, double min_gamma, v3 *u, double *e) {
    int l;
    if (m < 1 || m > MAXP || !(min_gamma > 0.0)) return -1;
    for (l = 0; l < m; l++) {
        const double *r = h + stride * l;
        double nn = sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2]);
        if (!(nn > 0.0) || !isfinite(nn)) return -1;
        u[l].x = r[0] / nn;
        u[l].y = r[1] / nn;
        u[l].z = r[2] / nn;
        if (e) e[l] = r[3] / nn;
    }
    return 0;
}

int polycc_bounded_without(const double *n, int m, double min_gamma, int8_t *state) {
    v3 u[MAXP];
    if (unit_rows(n, 3, m, min_gamma, u, NULL)) return -1;
    bounded_states(u, m, min_gamma, state);
    return 0;
}

static int by_key(const void *pa, const void *pb) {
    const entry *a = pa, *b = pb;
    if (a->key != b->key) return a->key < b->key ? -1 : 1;
    return (a->idx > b->idx) - (a->idx < b->idx);
}

static int by_planes(const void *pa, const void *pb) {
    const vertex *a = pa, *b = pb;
    if (a->vj != b->vj) return a->vj < b->vj ? -1 : 1;
    return (a->on > b->on) - (a->on < b->on);
}

static int by_angle(const void *pa, const void *pb) {
    const corner *a = pa, *b = pb;
    return (a->ang > b->ang) - (a->ang < b->ang);
}

/* Area of the convex polygon through pts[ix[0 .. k-1]] (any order, repeats allowed) in the plane of unit
 * normal nl: shoelace in angular order around the points' mean. */
static double face_area(const vertex *pts, const entry *ix, int k, v3 nl, corner *buf) {
    v3 g = {0.0, 0.0, 0.0}, helper = {0.0, 0.0, 0.0}, e1, e2;
    double len, sum = 0.0;
    int i;
    for (i = 0; i < k; i++) {
        g.x += pts[ix[i].idx].p.x;
        g.y += pts[ix[i].idx].p.y;
        g.z += pts[ix[i].idx].p.z;
    }
    g.x /= k;
    g.y /= k;
    g.z /= k;
    if (fabs(nl.x) < 0.9)
        helper.x = 1.0;
    else
        helper.y = 1.0;
    e1 = cross(nl, helper);
    len = sqrt(dot(e1, e1));
    e1.x /= len;
    e1.y /= len;
    e1.z /= len;
    e2 = cross(nl, e1);
    for (i = 0; i < k; i++) {
        v3 r = pts[ix[i].idx].p;
        r.x -= g.x;
        r.y -= g.y;
        r.z -= g.z;
        buf[i].x = dot(r, e1);
        buf[i].y = dot(r, e2);
        buf[i].ang = atan2(buf[i].y, buf[i].x);
    }
    qsort(buf, (size_t)k, sizeof(corner), by_angle);
    for (i = 0; i < k; i++) {
        const corner *a = &buf[i], *b = &buf[(i + 1) % k];
        sum += a->x * b->y - b->x * a->y;
    }
    return fabs(0.5 * sum);
}

int polycc_cap_volumes(const double *h, int m, double min_gamma, double *vol, int8_t *state) {
    static const double s3 = 0.57735026918962573; /* 1 / sqrt(3) */
    v3 n[MAXP], apex[MAXP];
    double e[MAXP], emax = 0.0, tol, fx[14], fy[14], fz[14], fe[14];
    int cnt[MAXP], has[MAXP], few[14], nfew = 0, any = 0, a, b, c, l, i, kept, np = 0, cap = 256, ne = 0, rc = 0;
    vertex *pts = NULL;
    v3 *cr = NULL;
    entry *ent = NULL;
    corner *buf = NULL;
    if (unit_rows(h, 4, m, min_gamma, n, e)) return -1;
    for (l = 0; l < m; l++) {
        emax = fmax(emax, fabs(e[l]));
        vol[l] = 0.0;
        cnt[l] = 0;
        has[l] = 0;
        apex[l].x = apex[l].y = apex[l].z = 0.0;
    }
    bounded_states(n, m, min_gamma, state);
    if (m <= MIN_PLANES) return 0;
    tol = TOL_REL * fmax(1.0, emax);
    /* most triples' points lie beyond several planes: the planes facing the box's 6 faces and 8 corners
     * reject them before the full test */
    for (i = 0; i < 14; i++) {
        v3 d = {0.0, 0.0, 0.0};
        double best = -INFINITY;
        int arg = 0, dup = 0, k;
        if (i < 6) {
            double s = i < 3 ? 1.0 : -1.0;
            if (i % 3 == 0) d.x = s;
            if (i % 3 == 1) d.y = s;
            if (i % 3 == 2) d.z = s;
        } else {
            d.x = ((i - 6) & 4) ? s3 : -s3;
            d.y = ((i - 6) & 2) ? s3 : -s3;
            d.z = ((i - 6) & 1) ? s3 : -s3;
        }
        for (l = 0; l < m; l++) {
            double sc = dot(d, n[l]);
            if (sc > best) {
                best = sc;
                arg = l;
            }
        }
        for (k = 0; k < nfew; k++) dup |= few[k] == arg;
        if (!dup) few[nfew++] = arg;
    }
    for (i = 0; i < nfew; i++) {
        fx[i] = n[few[i]].x;
        fy[i] = n[few[i]].y;
        fz[i] = n[few[i]].z;
        fe[i] = e[few[i]];
    }
    pts = malloc((size_t)cap * sizeof(vertex));
    cr = malloc((size_t)(m * m) * sizeof(v3));
    if (!pts || !cr) {
        rc = -1;
        goto done;
    }
    for (a = 0; a < m; a++)
        for (b = a + 1; b < m; b++) cr[a * m + b] = cross(n[a], n[b]);
    for (a = 0; a < m; a++)
        for (b = a + 1; b < m; b++)
            for (c = b + 1; c < m; c++) {
                /* meet() with the pairs' cross products from the table (c x a = -(a x c), exactly) */
                v3 p, bc = cr[b * m + c], ac = cr[a * m + c], ab = cr[a * m + b];
                mask on = 0;
                int nv = 0, vj = -1, k;
                double det = dot(n[a], bc);
                if (!(fabs(det) > DET_MIN)) continue;
                p.x = (e[a] * bc.x + e[b] * -ac.x + e[c] * ab.x) / det;
                p.y = (e[a] * bc.y + e[b] * -ac.y + e[c] * ab.y) / det;
                p.z = (e[a] * bc.z + e[b] * -ac.z + e[c] * ab.z) / det;
                /* the planes facing the box's faces and corners first: a point beyond two planes is no vertex
                 * of P or of a cap */
                for (k = 0; k < nfew; k++) /* branch-free: the compiler vectorises it */
                    nv += fx[k] * p.x + fy[k] * p.y + fz[k] * p.z - fe[k] > tol;
                if (nv > 1) continue;
                nv = 0;
                for (l = 0; l < m; l++) {
                    double s = dot(n[l], p) - e[l];
                    if (s > tol) {
                        vj = l;
                        if (++nv > 1) break;
                    } else if (fabs(s) <= tol) {
                        on |= (mask)1 << l;
                    }
                }
                if (nv > 1) continue;
                if (np == cap) {
                    vertex *more = realloc(pts, (size_t)cap * 2 * sizeof(vertex));
                    if (!more) {
                        rc = -1;
                        goto done;
                    }
                    pts = more;
                    cap *= 2;
                }
                pts[np].p = p;
                pts[np].vj = nv ? vj : -1;
                pts[np].on = on;
                np++;
            }
    /* a vertex on more than three planes comes from every triple of them that meets in a point: keep one per
     * (violated plane, planes it lies on), which is one per point (three of those planes meet only there) */
    qsort(pts, (size_t)np, sizeof(vertex), by_planes);
    for (i = 1, kept = np > 0; i < np; i++)
        if (pts[i].vj != pts[kept - 1].vj || pts[i].on != pts[kept - 1].on) pts[kept++] = pts[i];
    np = kept;
    for (i = 0; i < np; i++) {
        if (pts[i].vj >= 0) {
            has[pts[i].vj] = 1;
            any = 1;
            continue;
        }
        for (l = 0; l < m; l++)
            if (pts[i].on >> l & 1) {
                apex[l].x += pts[i].p.x;
                apex[l].y += pts[i].p.y;
                apex[l].z += pts[i].p.z;
                cnt[l]++;
            }
    }
    if (!any) goto done;
    /* the faces (j, l) of the caps: a cap vertex on plane l, or a vertex of P on planes j and l */
    for (int pass = 0; pass < 2; pass++) {
        ne = 0;
        for (i = 0; i < np; i++) {
            mask on = pts[i].on;
            if (pts[i].vj >= 0) {
                for (l = 0; l < m; l++)
                    if (on >> l & 1) {
                        if (pass) ent[ne] = (entry){pts[i].vj * m + l, i};
                        ne++;
                    }
                continue;
            }
            for (a = 0; a < m; a++) {
                if (!(on >> a & 1) || !has[a]) continue;
                for (l = 0; l < m; l++)
                    if (l != a && (on >> l & 1)) {
                        if (pass) ent[ne] = (entry){a * m + l, i};
                        ne++;
                    }
            }
        }
        if (!pass) {
            ent = malloc((size_t)(ne > 0 ? ne : 1) * sizeof(entry));
            buf = malloc((size_t)(ne > 0 ? ne : 1) * sizeof(corner));
            if (!ent || !buf) {
                rc = -1;
                goto done;
            }
        }
    }
    qsort(ent, (size_t)ne, sizeof(entry), by_key);
    for (i = 0; i < ne;) {
        int k = i, j, fl;
        double area, height;
        v3 ap;
        while (k < ne && ent[k].key == ent[i].key) k++;
        j = ent[i].key / m;
        fl = ent[i].key % m;
        area = face_area(pts, ent + i, k - i, n[fl], buf);
        ap = apex[j];
        ap.x /= (cnt[j] > 0 ? cnt[j] : 1);
        ap.y /= (cnt[j] > 0 ? cnt[j] : 1);
        ap.z /= (cnt[j] > 0 ? cnt[j] : 1);
        height = fmax(e[fl] - dot(n[fl], ap), 0.0);
        vol[j] += area * height / 3.0;
        i = k;
    }
done:
    free(pts);
    free(cr);
    free(ent);
    free(buf);
    return rc;
}
