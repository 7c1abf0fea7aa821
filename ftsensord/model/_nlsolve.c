/* The nonlinear estimator's solve in C: `NonlinearEstimator._solve` of nonlinear.py
 * (Levenberg-Marquardt and chord steps on SE(3), left perturbations T <- exp(delta) T)
 * with its forward model (fluxmodel.py: dipoles, each chip's own magnet's octupole,
 * per-chip response and offset, a uniform background field), its analytic Jacobian and
 * the steps' exp and log (se3floats.py). Same formulas, same order of decisions, same
 * tolerances (handed in by the caller from nonlinear.py's constants every call).
 *
 * Plain C99, no Python headers: built into a shared library at install (setup.py,
 * optional) and called through ctypes (nlcompiled.py) with pointers to float64 arrays
 * the caller owns. No allocation, no callbacks, no globals: reentrant per state.
 * Units SI (T, m, rad); poses are 4x4 row-major; frames as fluxmodel.py's.
 */
#include <math.h>
#include <string.h>

#define NMAX 16         /* chips a sensor may have: the ring has 8 */
#define CMAX (3 * NMAX) /* flux channels */
#define PI 3.141592653589793 /* math.pi */
#define PMAX 9          /* unknowns: the pose's 6 and the background field's 3 */

/* nonlinear.py's tunables, in this order (nlcompiled.TUNABLES). */
enum {
    MAX_STEP_M, MAX_STEP_RAD, STEP_TOL, STEP_TOL_RAD, CONTRACTION, REUSE_M, REUSE_TRACE, REUSE_T,
    MAX_RESIDUAL_T, BACKGROUND_LIMIT_T, PRIOR_WEIGHT, LINEAR_STEP_T, UNDAMPED, SMALL_ANGLE, NEAR_PI,
    MAX_ITERATIONS, NTUNABLES
};

/* The model and the estimator's constants, all doubles (nlcompiled.LAYOUT packs it). */
typedef struct {
    double n, octupole, own_only, spare;
    double chip_p[NMAX][3], magnet_p[NMAX][3];
    double m[NMAX][3];          /* mu0/(4 pi) times each moment, T m^3 */
    double axis[NMAX][3];       /* unit magnetisation */
    double half_q[NMAX];        /* half the octupole strength, T m^5 */
    double inv_m[NMAX];         /* 1 / |m| */
    double resp[NMAX][3][3];    /* S R_chip^T */
    double offset[NMAX][3];     /* o, T */
    double K[6][6], zero_twist[6], plausible[6];
    double tun[NTUNABLES];
} nl_model;

/* A kept Jacobian (one per kind of solve: without and with the background field). */
typedef struct {
    int valid, factored, singular, has_u;
    long id;
    double rows[12], u[3];
    double J[CMAX][PMAX];
    double lu[PMAX][PMAX];      /* J^T J + P factored: the chord steps' solve */
    int piv[PMAX];
} nl_jacobian;

typedef struct {
    nl_jacobian jac[2];
    long next_id;
    double end_pred[CMAX];      /* the flux at the last converged fit's end */
} nl_state;

size_t nl_state_bytes(void) { return sizeof(nl_state); }
size_t nl_model_doubles(void) { return sizeof(nl_model) / sizeof(double); }

/* Python's max(a, b) and min(a, b): the first unless the second is strictly beyond (NaN kept). */
static double pymax(double a, double b) { return b > a ? b : a; }
static double pymin(double a, double b) { return b < a ? b : a; }

/* The magnets' field B (n, 3) at the chips where T puts them (p), and its gradient G. */
static void fields(const nl_model *M, const double *T, double B[][3], double G[][3][3], double p[][3])
{
    int n = (int)M->n;
    for (int i = 0; i < n; i++)
        for (int a = 0; a < 3; a++)
            p[i][a] = T[4 * a] * M->chip_p[i][0] + T[4 * a + 1] * M->chip_p[i][1] + T[4 * a + 2] * M->chip_p[i][2]
                      + T[4 * a + 3];
    for (int i = 0; i < n; i++) {
        double Bi[3] = {0, 0, 0}, W[3][3] = {{0}}, V[3][3] = {{0}}, diag = 0, oct = 0;
        int j0 = M->own_only != 0 ? i : 0, j1 = M->own_only != 0 ? i + 1 : n;
        for (int j = j0; j < j1; j++) {
            const double *mj = M->m[j];
            double r[3] = {p[i][0] - M->magnet_p[j][0], p[i][1] - M->magnet_p[j][1], p[i][2] - M->magnet_p[j][2]};
            double d2 = r[0] * r[0] + r[1] * r[1] + r[2] * r[2];
            double inv = 1.0 / d2, k3 = inv * sqrt(inv), k5 = k3 * inv;
            double rm3 = 3 * (r[0] * mj[0] + r[1] * mj[1] + r[2] * mj[2]);
            double a = k5 * rm3;  /* B = sum_m 3 (r.m) r / d^5 - m / d^3 (m with mu0/(4 pi)) */
            double w = 3 * k5, v = -5 * a * inv;
            for (int c = 0; c < 3; c++)
                Bi[c] += a * r[c] - k3 * mj[c];
            diag += a;
            if (j == i && M->octupole != 0) {
                /* magnet.octupole_field on the own pair: B = q/2 (A r - C n) */
                const double *ax = M->axis[i];
                double s = r[0] * ax[0] + r[1] * ax[1] + r[2] * ax[2];
                double c2 = s * s * inv, hq = M->half_q[i] * k5 * inv;
                double a_own = hq * s * (35 * c2 - 15);
                for (int c = 0; c < 3; c++)
                    Bi[c] += a_own * r[c] - hq * (15 * c2 - 3) / inv * ax[c];
                w += hq * (105 * c2 - 15) * M->inv_m[i];
                v += hq * s * inv * (105 - 315 * c2);
                diag += a_own;
                oct = 30 * hq * s;
            }
            for (int k = 0; k < 3; k++)
                for (int l = 0; l < 3; l++) {
                    W[k][l] += w * mj[k] * r[l];
                    V[k][l] += v * r[k] * r[l];
                }
        }
        memcpy(B[i], Bi, sizeof Bi);
        if (G == NULL)
            continue;
        for (int k = 0; k < 3; k++)
            for (int l = 0; l < 3; l++)
                G[i][k][l] = W[k][l] + W[l][k] + V[k][l] + (k == l ? diag : 0.0) - oct * M->axis[i][k] * M->axis[i][l];
    }
}

/* Flux (3n) at (T, u): S R_chip^T R_T^T (B + u) + o. */
static void predict(const nl_model *M, const double *T, const double *u, double *out)
{
    double B[NMAX][3], p[NMAX][3];
    int n = (int)M->n;
    fields(M, T, B, NULL, p);
    for (int i = 0; i < n; i++) {
        double x[3];
        for (int c = 0; c < 3; c++)
            x[c] = B[i][c] + u[c];
        double y[3];
        for (int c = 0; c < 3; c++)  /* R_T^T x */
            y[c] = T[c] * x[0] + T[4 + c] * x[1] + T[8 + c] * x[2];
        for (int a = 0; a < 3; a++)
            out[3 * i + a] = M->resp[i][a][0] * y[0] + M->resp[i][a][1] * y[1] + M->resp[i][a][2] * y[2]
                             + M->offset[i][a];
    }
}

/* Flux and its derivative for T <- exp([v; w]) T (and u): db/dv = S R^T G,
 * db/dw = S R^T (hat(B + u) - G hat(p)), db/du = S R^T. */
static void predict_and_jacobian(const nl_model *M, const double *T, const double *u, double *out, double J[][PMAX])
{
    double B[NMAX][3], G[NMAX][3][3], p[NMAX][3];
    int n = (int)M->n;
    fields(M, T, B, G, p);
    for (int i = 0; i < n; i++) {
        double SRt[3][3], Bu[3], cols[3][9];
        for (int a = 0; a < 3; a++)
            for (int c = 0; c < 3; c++)  /* (S R_chip^T) R_T^T */
                SRt[a][c] = M->resp[i][a][0] * T[4 * c] + M->resp[i][a][1] * T[4 * c + 1] + M->resp[i][a][2] * T[4 * c + 2];
        for (int c = 0; c < 3; c++)
            Bu[c] = B[i][c] + u[c];
        double hB[3][3] = {{0, -Bu[2], Bu[1]}, {Bu[2], 0, -Bu[0]}, {-Bu[1], Bu[0], 0}};
        double hp[3][3] = {{0, -p[i][2], p[i][1]}, {p[i][2], 0, -p[i][0]}, {-p[i][1], p[i][0], 0}};
        for (int k = 0; k < 3; k++)
            for (int l = 0; l < 3; l++) {
                cols[k][l] = G[i][k][l];
                cols[k][3 + l] = hB[k][l] - (G[i][k][0] * hp[0][l] + G[i][k][1] * hp[1][l] + G[i][k][2] * hp[2][l]);
                cols[k][6 + l] = k == l;
            }
        for (int a = 0; a < 3; a++) {
            for (int col = 0; col < 9; col++)
                J[3 * i + a][col] = SRt[a][0] * cols[0][col] + SRt[a][1] * cols[1][col] + SRt[a][2] * cols[2][col];
            out[3 * i + a] = SRt[a][0] * Bu[0] + SRt[a][1] * Bu[1] + SRt[a][2] * Bu[2] + M->offset[i][a];
        }
    }
}

/* se3._coefficients: A = sin t / t, B = (1 - cos t) / t^2, C = (t - sin t) / t^3. */
static void coefficients(double theta, double small, double *a, double *b, double *c)
{
    if (theta < small) {
        double t2 = theta * theta;
        *a = 1 - t2 / 6 + t2 * t2 / 120;
        *b = 0.5 - t2 / 24 + t2 * t2 / 720;
        *c = 1.0 / 6 - t2 / 120 + t2 * t2 / 5040;
        return;
    }
    double s = sin(theta), co = cos(theta), t2 = theta * theta;  /* inf: NaN, as se3's */
    *a = s / theta, *b = (1 - co) / t2, *c = (theta - s) / (t2 * theta);
}

/* se3floats.exp_se3 of xi[:6], 3x4 rows into E. */
static void exp_se3(const double *xi, double small, double *E)
{
    double v0 = xi[0], v1 = xi[1], v2 = xi[2], w0 = xi[3], w1 = xi[4], w2 = xi[5];
    double ww = w0 * w0 + w1 * w1 + w2 * w2, a, b, c;
    coefficients(sqrt(ww), small, &a, &b, &c);
    double bw0 = b * w0, bw1 = b * w1, bw2 = b * w2, aw0 = a * w0, aw1 = a * w1, aw2 = a * w2;
    double wv = w0 * v0 + w1 * v1 + w2 * v2;
    double x0 = w1 * v2 - w2 * v1, x1 = w2 * v0 - w0 * v2, x2 = w0 * v1 - w1 * v0;
    double e[12] = {1.0 + bw0 * w0 - b * ww, bw0 * w1 - aw2, bw0 * w2 + aw1, v0 + b * x0 + c * (w0 * wv - ww * v0),
                    bw1 * w0 + aw2, 1.0 + bw1 * w1 - b * ww, bw1 * w2 - aw0, v1 + b * x1 + c * (w1 * wv - ww * v1),
                    bw2 * w0 - aw1, bw2 * w1 + aw0, 1.0 + bw2 * w2 - b * ww, v2 + b * x2 + c * (w2 * wv - ww * v2)};
    memcpy(E, e, sizeof e);
}

/* se3.log_se3 (se3floats' formulas short of pi, se3.log_so3's symmetric part within NEAR_PI of it). */
static void log_se3(const double *T, double small, double near_pi, double *xi)
{
    double r00 = T[0], r01 = T[1], r02 = T[2], r10 = T[4], r11 = T[5], r12 = T[6], r20 = T[8], r21 = T[9], r22 = T[10];
    double s0 = 0.5 * (r21 - r12), s1 = 0.5 * (r02 - r20), s2 = 0.5 * (r10 - r01);
    double sin_theta = sqrt(s0 * s0 + s1 * s1 + s2 * s2), co = 0.5 * (r00 + r11 + r22 - 1.0);
    double theta = atan2(sin_theta, co), w0, w1, w2;
    if (theta < small) {
        double t2 = theta * theta, k = 1 + t2 / 6 + 7 * t2 * t2 / 360;
        w0 = k * s0, w1 = k * s1, w2 = k * s2;
    } else if (PI - theta > near_pi) {
        double k = theta / sin_theta;
        w0 = k * s0, w1 = k * s1, w2 = k * s2;
    } else {  /* (R + R^T)/2 = cos(t) I + (1 - cos t) a a^T, well conditioned here */
        double R[3][3] = {{r00, r01, r02}, {r10, r11, r12}, {r20, r21, r22}}, aat[3][3], ax[3], s[3] = {s0, s1, s2};
        for (int i = 0; i < 3; i++)
            for (int j = 0; j < 3; j++)
                aat[i][j] = (0.5 * (R[i][j] + R[j][i]) - (i == j ? co : 0.0)) / (1.0 - co);
        int k = 0;
        for (int i = 1; i < 3; i++)
            if (aat[i][i] > aat[k][k])
                k = i;
        for (int i = 0; i < 3; i++)
            ax[i] = aat[i][k] / sqrt(aat[k][k]);
        int big = 0;
        for (int i = 1; i < 3; i++)
            if (fabs(ax[i]) > fabs(ax[big]))
                big = i;
        if ((sin_theta > 0 && ax[0] * s[0] + ax[1] * s[1] + ax[2] * s[2] < 0) || (sin_theta == 0 && ax[big] < 0))
            ax[0] = -ax[0], ax[1] = -ax[1], ax[2] = -ax[2];
        double norm = sqrt(ax[0] * ax[0] + ax[1] * ax[1] + ax[2] * ax[2]);
        w0 = theta * ax[0] / norm, w1 = theta * ax[1] / norm, w2 = theta * ax[2] / norm;
        theta = sqrt(w0 * w0 + w1 * w1 + w2 * w2);
    }
    double tt = theta * theta, d;
    if (theta < small)
        d = 1.0 / 12 + tt / 720 + tt * tt / 30240;
    else
        d = 1 / tt - 1 / (2 * theta * tan(theta / 2));
    double t0 = T[3], t1 = T[7], t2 = T[11];  /* J_l(w)^-1 t = t - (w x t) / 2 + D w x (w x t) */
    double c0 = w1 * t2 - w2 * t1, c1 = w2 * t0 - w0 * t2, c2 = w0 * t1 - w1 * t0;
    double cc0 = w1 * c2 - w2 * c1, cc1 = w2 * c0 - w0 * c2, cc2 = w0 * c1 - w1 * c0;
    xi[0] = t0 - 0.5 * c0 + d * cc0, xi[1] = t1 - 0.5 * c1 + d * cc1, xi[2] = t2 - 0.5 * c2 + d * cc2;
    xi[3] = w0, xi[4] = w1, xi[5] = w2;
}

/* LU with partial pivoting (LAPACK's getrf: the first largest pivot); 0 when a pivot is
 * exactly zero, where numpy's solve raises LinAlgError. */
static int lu_factor(double A[][PMAX], int *piv, int m)
{
    int ok = 1;
    for (int k = 0; k < m; k++) {
        int best = k;
        for (int i = k + 1; i < m; i++)
            if (fabs(A[i][k]) > fabs(A[best][k]))
                best = i;
        piv[k] = best;
        if (best != k)
            for (int j = 0; j < m; j++) {
                double t = A[k][j];
                A[k][j] = A[best][j], A[best][j] = t;
            }
        if (A[k][k] == 0.0) {
            ok = 0;
            continue;
        }
        for (int i = k + 1; i < m; i++) {
            double l = A[i][k] /= A[k][k];
            for (int j = k + 1; j < m; j++)
                A[i][j] -= l * A[k][j];
        }
    }
    return ok;
}

static void lu_solve(double A[][PMAX], const int *piv, int m, double *x)
{
    for (int k = 0; k < m; k++) {  /* the row swaps first: they moved L's rows too */
        double t = x[k];
        x[k] = x[piv[k]], x[piv[k]] = t;
    }
    for (int k = 0; k < m; k++)
        for (int i = k + 1; i < m; i++)
            x[i] -= A[i][k] * x[k];
    for (int k = m - 1; k >= 0; k--) {
        for (int j = k + 1; j < m; j++)
            x[k] -= A[k][j] * x[j];
        x[k] /= A[k][k];
    }
}

/* J^T J and J^T r over the used channels (r is zero elsewhere), with the background
 * field's prior rows (noise / prior) (u + du) = 0: nonlinear._normal. */
static void normal(double J[][PMAX], const double *r, const int *used, int nc, int p, const double *u,
                   double pw, double JtJ[][PMAX], double *Jtr)
{
    for (int a = 0; a < p; a++) {
        Jtr[a] = 0;
        for (int b = 0; b < p; b++)
            JtJ[a][b] = 0;
    }
    for (int c = 0; c < nc; c++) {
        if (!used[c])
            continue;
        for (int a = 0; a < p; a++) {
            Jtr[a] += J[c][a] * r[c];
            for (int b = 0; b < p; b++)
                JtJ[a][b] += J[c][a] * J[c][b];
        }
    }
    if (p == 9)
        for (int a = 0; a < 3; a++)
            JtJ[6 + a][6 + a] += pw, Jtr[6 + a] -= pw * u[a];
}

/* nonlinear._near: pose within REUSE_M and the trace test's turn (and the field within REUSE_T). */
static int near(const double *T, const nl_jacobian *K, const double *u, int with_u, const double *tun)
{
    const double *d = K->rows;
    double trace = 0, dist2 = 0, du2 = 0;
    for (int i = 0; i < 3; i++) {
        for (int j = 0; j < 3; j++)
            trace += T[4 * i + j] * d[4 * i + j];
        dist2 += (T[4 * i + 3] - d[4 * i + 3]) * (T[4 * i + 3] - d[4 * i + 3]);
    }
    if (!(trace >= tun[REUSE_TRACE] && sqrt(dist2) <= tun[REUSE_M]))
        return 0;
    if (!with_u)
        return 1;
    for (int i = 0; i < 3; i++)
        du2 += (K->u[i] - u[i]) * (K->u[i] - u[i]);
    return K->has_u && sqrt(du2) <= tun[REUSE_T];
}

static int within(const double *size, const double *tun)
{
    return size[0] < tun[STEP_TOL] && size[1] < tun[STEP_TOL_RAD];
}

/* nonlinear._left: the steps left foretold from this one and the last (inf where unseen). */
static void left(const double *size, const double *last, double contraction, double *out)
{
    out[0] = out[1] = INFINITY;
    if (pymin(last[0], last[1]) <= 0)
        return;
    double ratio = pymax(size[0] / last[0], size[1] / last[1]);
    if (ratio > contraction)
        return;
    out[0] = size[0] * ratio / (1 - ratio), out[1] = size[1] * ratio / (1 - ratio);
}

/* Residual over the used channels (zero elsewhere) and the cost with the prior. */
static double residual(const double *b, const double *pred, const int *used, int nc, const double *u, int bg,
                       double pw, double *r)
{
    double cost = 0;
    for (int c = 0; c < nc; c++) {
        r[c] = used[c] ? b[c] - pred[c] : 0.0;
        cost += r[c] * r[c];
    }
    return bg ? cost + pw * (u[0] * u[0] + u[1] * u[1] + u[2] * u[2]) : cost;
}

/* One fit: nonlinear.NonlinearEstimator._solve. In: b (3n), usable (n, nonzero: used; NULL:
 * all), T (16) the start, u (3) the background field's start, end_known: the state's
 * end_pred is the flux at (T, u). Out: T, u (zeros without the field), out = [xi (6),
 * rms (T), iterations, converged]. Returns 0. */
int nl_solve(const nl_model *M, nl_state *S, const double *b, const double *usable, double *T, double *u,
             int background, double damping, int end_known, double *out)
{
    const double *tun = M->tun;
    int n = (int)M->n, nc = 3 * n, p = background ? 9 : 6, used_n = 0, finite = 1, max_it = (int)tun[MAX_ITERATIONS];
    int used[CMAX];
    double uc[3] = {0, 0, 0}, pw = tun[PRIOR_WEIGHT];
    if (background)
        memcpy(uc, u, sizeof uc);
    for (int c = 0; c < nc; c++) {
        used[c] = usable == NULL || usable[c / 3] != 0;
        used_n += used[c];
        if (used[c] && !isfinite(b[c]))
            finite = 0;
    }
    if (used_n < p || !finite) {  /* the unknowns need as many channels */
        log_se3(T, tun[SMALL_ANGLE], tun[NEAR_PI], out);
        out[6] = INFINITY, out[7] = 0, out[8] = 0;
        u[0] = u[1] = u[2] = 0;
        return 0;
    }
    nl_jacobian *K = &S->jac[background ? 1 : 0];
    double lam = damping, cost = INFINITY, pred[CMAX], r[CMAX], size[2] = {0, 0}, scale = 1, last_size[2] = {0, 0};
    int done = 0, final = 0, k = 0, have_pred = end_known, r_valid = 0, have_last = 0, last_fresh = 0;
    long last_id = -1;
    if (end_known)
        memcpy(pred, S->end_pred, sizeof(double) * nc);
    for (int it = 1; it <= max_it; it++) {
        k = it;
        int fresh = 0, cleared = 0;
        if (K->valid && near(T, K, uc, background, tun)) {
            if (!have_pred)
                predict(M, T, uc, pred), have_pred = 1, r_valid = 0;
        } else {
            predict_and_jacobian(M, T, uc, pred, K->J);
            memcpy(K->rows, T, sizeof K->rows), memcpy(K->u, uc, sizeof uc);
            K->has_u = background, K->valid = 1, K->factored = 0, K->id = ++S->next_id;
            fresh = 1, have_pred = 1, r_valid = 0;
        }
        if (!r_valid)
            cost = residual(b, pred, used, nc, uc, background, pw, r), r_valid = 1;
        int chord = used_n == nc && (!fresh || lam <= tun[UNDAMPED]);  /* Gauss-Newton's gains serve */
        double JtJ[PMAX][PMAX], Jtr[PMAX], step[PMAX], Tn[16], un[3], pn[CMAX], rn[CMAX];
        if (!chord)
            normal(K->J, r, used, nc, p, uc, pw, JtJ, Jtr);
        long id = K->id;
        for (;;) {
            int solvable;
            if (chord) {  /* (J^T J + P)^-1 (J^T r - P u), J^T J + P factored once per Jacobian */
                if (!K->factored) {
                    double rhs[PMAX];
                    normal(K->J, r, used, nc, p, uc, pw, K->lu, rhs);
                    K->singular = !lu_factor(K->lu, K->piv, p), K->factored = 1;
                }
                solvable = !K->singular;
                if (solvable) {
                    for (int a = 0; a < p; a++) {
                        step[a] = 0;
                        for (int c = 0; c < nc; c++)
                            step[a] += K->J[c][a] * r[c];
                    }
                    if (background)
                        for (int a = 0; a < 3; a++)
                            step[6 + a] -= pw * uc[a];
                    lu_solve(K->lu, K->piv, p, step);
                }
            } else {  /* JtJ + lam diag(JtJ) */
                double damped[PMAX][PMAX];
                int piv[PMAX];
                memcpy(damped, JtJ, sizeof damped);
                for (int a = 0; a < p; a++)
                    damped[a][a] *= 1 + lam;
                solvable = lu_factor(damped, piv, p);
                if (solvable)
                    memcpy(step, Jtr, sizeof(double) * p), lu_solve(damped, piv, p, step);
            }
            if (!solvable) {  /* J^T J singular (a pose no chip sees move): a refusal */
                log_se3(T, tun[SMALL_ANGLE], tun[NEAR_PI], out);
                out[6] = sqrt(cost / used_n), out[7] = it, out[8] = 0;
                memcpy(u, uc, sizeof uc);
                return 0;
            }
            size[0] = sqrt(step[0] * step[0] + step[1] * step[1] + step[2] * step[2]);
            size[1] = sqrt(step[3] * step[3] + step[4] * step[4] + step[5] * step[5]);
            /* 1e-300: a zero step needs no limit (and must not divide by zero) */
            scale = pymin(pymin(1.0, tun[MAX_STEP_M] / pymax(size[0], 1e-300)), tun[MAX_STEP_RAD] / pymax(size[1], 1e-300));
            if (scale < 1.0) {
                for (int a = 0; a < p; a++)
                    step[a] *= scale;
                size[0] *= scale, size[1] *= scale;
            }
            double E[12];
            exp_se3(step, tun[SMALL_ANGLE], E);
            for (int i = 0; i < 3; i++)
                for (int j = 0; j < 4; j++)
                    Tn[4 * i + j] = E[4 * i] * T[j] + E[4 * i + 1] * T[4 + j] + E[4 * i + 2] * T[8 + j] + (j == 3 ? E[4 * i + 3] : 0.0);
            Tn[12] = Tn[13] = Tn[14] = 0.0, Tn[15] = 1.0;
            for (int a = 0; a < 3; a++)
                un[a] = background ? uc[a] + step[6 + a] : 0.0;
            final = within(size, tun);
            if (!final && have_last && ((last_fresh && fresh) || last_id == id)) {
                double l[2];
                left(size, last_size, tun[CONTRACTION], l);
                final = within(l, tun);
            }
            int linear = 0;
            if (final) {  /* the last step, too small to need the field (LINEAR_STEP_T) */
                double worst = 0;
                int nan = 0;  /* a NaN change is no small one (numpy's max is NaN, not below) */
                for (int c = 0; c < nc; c++) {
                    double ch = 0;
                    for (int a = 0; a < p; a++)
                        ch += K->J[c][a] * step[a];
                    pn[c] = pred[c] + ch;
                    nan |= isnan(ch);
                    worst = pymax(worst, fabs(ch));
                }
                linear = !nan && worst <= tun[LINEAR_STEP_T];
            }
            if (!linear)
                predict(M, Tn, un, pn);
            double cost_new = residual(b, pn, used, nc, un, background, pw, rn);
            if (cost_new <= cost) {
                memcpy(T, Tn, sizeof Tn), memcpy(uc, un, sizeof un), memcpy(pred, pn, sizeof(double) * nc);
                memcpy(r, rn, sizeof(double) * nc);
                lam = pymax(lam / 3, 1e-9), cost = cost_new;
                break;
            }
            if (within(size, tun)) {  /* at the minimum already */
                done = 1;
                break;
            }
            if (!fresh) {  /* a kept Jacobian's step failed: a new one, not more damping */
                S->jac[0].valid = S->jac[1].valid = 0, cleared = 1;
                break;
            }
            lam *= 4;
            if (chord) {  /* a new Jacobian's undamped step failed: damped solves from here */
                chord = 0;
                normal(K->J, r, used, nc, p, uc, pw, JtJ, Jtr);
            }
            if (lam > 1e8) {  /* no step lowers the cost: a minimum, or hopeless data */
                done = 1;
                break;
            }
        }
        if (cleared)
            continue;
        if (done || final)
            break;
        have_last = scale == 1.0;  /* a limited step says nothing of convergence */
        last_size[0] = size[0], last_size[1] = size[1], last_fresh = fresh, last_id = id;
    }
    double prior = background ? pw * (uc[0] * uc[0] + uc[1] * uc[1] + uc[2] * uc[2]) : 0.0;
    double rms = sqrt(pymax(cost - prior, 0.0) / used_n);  /* of the flux alone */
    log_se3(T, tun[SMALL_ANGLE], tun[NEAR_PI], out);
    int plausible = sqrt(uc[0] * uc[0] + uc[1] * uc[1] + uc[2] * uc[2]) <= tun[BACKGROUND_LIMIT_T] || !background;
    for (int a = 0; a < 6; a++) {
        double w = 0;
        for (int c = 0; c < 6; c++)
            w += M->K[a][c] * (out[c] - M->zero_twist[c]);
        plausible = plausible && fabs(w) <= M->plausible[a];
    }
    int converged = isfinite(rms) && rms <= tun[MAX_RESIDUAL_T] && plausible && (done || k < max_it);
    if (converged)
        memcpy(S->end_pred, pred, sizeof(double) * nc);
    out[6] = rms, out[7] = k, out[8] = converged;
    memcpy(u, uc, sizeof uc);
    return 0;
}

/* The forward model alone, for tests: flux (3n) at (T, u) and its derivative (3n x 9, rows of 9). */
void nl_predict_and_jacobian(const nl_model *M, const double *T, const double *u, double *pred, double *J)
{
    predict_and_jacobian(M, T, u, pred, (double (*)[PMAX])J);
}

void nl_predict(const nl_model *M, const double *T, const double *u, double *pred) { predict(M, T, u, pred); }
