/* The nonlinear estimator's solve in C: `NonlinearEstimator._solve` of nonlinear.py
 * (Levenberg-Marquardt and chord steps on SE(3), left perturbations T <- exp(delta) T) on
 * the forward model of _nlmodel.c. Same steps, same order of decisions, same tolerances
 * (handed in by the caller from nonlinear.py's constants every call).
 *
 * Plain C99, no Python headers: built at install into a shared library (setup.py,
 * optional) and called through ctypes (nlcompiled.py) with pointers to float64 arrays
 * the caller owns. No allocation, no callbacks, no globals: reentrant per state.
 */
#include <math.h>
#include <stddef.h>
#include <string.h>

#include "_nlsolve.h"

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

/* nl_model's layout for the loader's check (nlcompiled.load), field by field as LAYOUT
 * names them: the offset in doubles of the field called ``name``, or -1. */
long nl_model_offset(const char *name) {
    static const struct { const char *name; size_t at; } fields[] = {
        {"head", offsetof(nl_model, n)}, {"chip_p", offsetof(nl_model, chip_p)},
        {"magnet_p", offsetof(nl_model, magnet_p)}, {"m", offsetof(nl_model, m)},
        {"axis", offsetof(nl_model, axis)}, {"half_q", offsetof(nl_model, half_q)},
        {"inv_m", offsetof(nl_model, inv_m)}, {"resp", offsetof(nl_model, resp)},
        {"offset", offsetof(nl_model, offset)}, {"K", offsetof(nl_model, K)},
        {"zero_twist", offsetof(nl_model, zero_twist)}, {"plausible", offsetof(nl_model, plausible)},
        {"tun", offsetof(nl_model, tun)},
    };
    for (size_t i = 0; i < sizeof fields / sizeof fields[0]; i++)
        if (!strcmp(name, fields[i].name)) return (long)(fields[i].at / sizeof(double));
    return -1;
}

/* The index of the tunable called ``name`` in nl_model.tun (NL_TUNABLES' order), or -1. */
long nl_tunable_index(const char *name) {
#define NL_NAME(n) #n,
    static const char *const names[] = {NL_TUNABLES(NL_NAME)};
#undef NL_NAME
    for (long i = 0; i < NTUNABLES; i++)
        if (!strcmp(name, names[i])) return i;
    return -1;
}

/* Python's max(a, b) and min(a, b): the first unless the second is strictly beyond (NaN kept). */
static double pymax(double a, double b) { return b > a ? b : a; }
static double pymin(double a, double b) { return b < a ? b : a; }

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

/* A X = B solved in place for B's n columns (m rows, row i from x + i * stride), A factored by
 * lu_factor. Each column takes the same operations in the same order as it would alone; the
 * columns are the innermost loop, so the compiler runs them side by side (the chord gains'
 * 3n columns one after the other waited on each other's divisions: most of the sigma's cost). */
static void lu_solve(double A[][PMAX], const int *piv, int m, double *restrict x, int n, int stride)
{
    for (int k = 0; k < m; k++) {  /* the row swaps first: they moved L's rows too */
        double *restrict row = x + k * stride, *restrict other = x + piv[k] * stride;
        if (piv[k] != k)
            for (int c = 0; c < n; c++) {
                double t = row[c];
                row[c] = other[c], other[c] = t;
            }
    }
    for (int k = 0; k < m; k++)
        for (int i = k + 1; i < m; i++) {
            double l = A[i][k];
            for (int c = 0; c < n; c++)
                x[i * stride + c] -= l * x[k * stride + c];
        }
    for (int k = m - 1; k >= 0; k--) {
        for (int j = k + 1; j < m; j++) {
            double u = A[k][j];
            for (int c = 0; c < n; c++)
                x[k * stride + c] -= u * x[j * stride + c];
        }
        double d = A[k][k];
        for (int c = 0; c < n; c++)
            x[k * stride + c] /= d;
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

/* nonlinear.NonlinearEstimator._kept_jacobian: the Jacobian kept in K when (T, u) is near
 * where it was made (0), else a new one made there, with the flux at (T, u) into pred (1). */
static int linearise(const nl_model *M, nl_state *S, nl_jacobian *K, const double *T, const double *u,
                     int background, double *pred)
{
    if (K->valid && near(T, K, u, background, M->tun))
        return 0;
    nlm_predict_and_jacobian(M, T, u, pred, K->J);
    memcpy(K->rows, T, sizeof K->rows), memcpy(K->u, u, sizeof K->u);
    K->has_u = background, K->valid = 1, K->factored = 0, K->id = ++S->next_id;
    return 1;
}

/* The Jacobian a solve with the background field keeps (linearise) at T (16) and field u (3),
 * into J (3n x PMAX, row-major): made anew only where a solve would make one, and kept for
 * the solves after. Returns its id (S->next_id when it was made, unique in this state): what
 * was made from it is still its own while the id is the same. nonlinear.NonlinearEstimator.jacobian_at. */
long nl_kept_jacobian(const nl_model *M, nl_state *S, const double *T, const double *u, double *J)
{
    double pred[CMAX];
    nl_jacobian *K = &S->jac[1];
    linearise(M, S, K, T, u, 1, pred);
    memcpy(J, K->J, sizeof(double) * 3 * (size_t)M->n * PMAX);
    return K->id;
}

/* nonlinear.NonlinearEstimator.gains with every channel: G = (J^T J + P)^-1 J^T into G (PMAX x
 * CMAX, row-major) for J (3n x PMAX, row-major) with the background field's columns, from the
 * factors the chord steps keep when J is the state's kept Jacobian (factored and kept there
 * when not yet), else from J's own. 0 when J^T J + P is singular. */
int nl_chord_gains(const nl_model *M, nl_state *S, const double *J, double *G)
{
    int nc = 3 * (int)M->n, used[CMAX];
    double r[CMAX], u[3] = {0, 0, 0}, rhs[PMAX];
    for (int c = 0; c < nc; c++)
        used[c] = 1, r[c] = 0.0;
    nl_jacobian *K = &S->jac[1], own;
    if (!(K->valid && !memcmp(K->J, J, sizeof(double) * nc * PMAX))) {
        memcpy(own.J, J, sizeof(double) * nc * PMAX);
        own.factored = 0, K = &own;
    }
    if (!K->factored) {
        normal(K->J, r, used, nc, PMAX, u, M->tun[PRIOR_WEIGHT], K->lu, rhs);
        K->singular = !lu_factor(K->lu, K->piv, PMAX), K->factored = 1;
    }
    if (K->singular)
        return 0;
    for (int a = 0; a < PMAX; a++)  /* J^T, solved for in place: all its columns at once */
        for (int c = 0; c < nc; c++)
            G[a * CMAX + c] = K->J[c][a];
    lu_solve(K->lu, K->piv, PMAX, G, nc, CMAX);
    return 1;
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
        nlm_log_se3(T, tun[SMALL_ANGLE], tun[NEAR_PI], out);
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
        int fresh = linearise(M, S, K, T, uc, background, pred), cleared = 0;
        if (fresh)
            have_pred = 1, r_valid = 0;
        else if (!have_pred)
            nlm_predict(M, T, uc, pred), have_pred = 1, r_valid = 0;
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
                    lu_solve(K->lu, K->piv, p, step, 1, 1);
                }
            } else {  /* JtJ + lam diag(JtJ) */
                double damped[PMAX][PMAX];
                int piv[PMAX];
                memcpy(damped, JtJ, sizeof damped);
                for (int a = 0; a < p; a++)
                    damped[a][a] *= 1 + lam;
                solvable = lu_factor(damped, piv, p);
                if (solvable)
                    memcpy(step, Jtr, sizeof(double) * p), lu_solve(damped, piv, p, step, 1, 1);
            }
            if (!solvable) {  /* J^T J singular (a pose no chip sees move): a refusal */
                nlm_log_se3(T, tun[SMALL_ANGLE], tun[NEAR_PI], out);
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
            nlm_exp_se3(step, tun[SMALL_ANGLE], E);
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
                nlm_predict(M, Tn, un, pn);
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
    nlm_log_se3(T, tun[SMALL_ANGLE], tun[NEAR_PI], out);
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
