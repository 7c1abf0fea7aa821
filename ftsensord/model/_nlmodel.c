/* The nonlinear estimator's forward model in C: fluxmodel.py's FluxModel (dipoles, each
 * chip's own magnet's octupole, per-chip response S R_chip^T and offset, a uniform
 * background field u) with its analytic Jacobian, and se3.py's exp and log: the same
 * formulas, in the same order where it matters. Part of the compiled solve (_nlsolve.c).
 * Units SI (T, m, rad); poses 4x4 row-major; frames as fluxmodel.py's. */
#include <math.h>
#include <string.h>

#include "_nlsolve.h"

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
void nlm_predict(const nl_model *M, const double *T, const double *u, double *out)
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
void nlm_predict_and_jacobian(const nl_model *M, const double *T, const double *u, double *out, double J[][PMAX])
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

/* se3.exp_se3 of xi[:6], 3x4 rows into E. */
void nlm_exp_se3(const double *xi, double small, double *E)
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

/* se3.log_se3 (the float formulas short of pi, se3.log_so3's symmetric part within NEAR_PI of it). */
void nlm_log_se3(const double *T, double small, double near_pi, double *xi)
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


/* The forward model alone, for tests: flux (3n) at (T, u) and its derivative (3n x 9, rows of 9). */
void nl_predict_and_jacobian(const nl_model *M, const double *T, const double *u, double *pred, double *J)
{
    nlm_predict_and_jacobian(M, T, u, pred, (double (*)[PMAX])J);
}

void nl_predict(const nl_model *M, const double *T, const double *u, double *pred) { nlm_predict(M, T, u, pred); }

/* se3.continued: ``pose`` moved on by the motion from ``before`` to it (4x4 each),
 * T_k (T_k-1)^-1 T_k taken as a twist, into ahead (4x4); that twist's translation (m) and
 * turn (rad) into sizes. */
void nl_continued(const double *before, const double *pose, double small, double near_pi, double *ahead,
                  double *sizes)
{
    double D[16] = {0}, step[6], E[12];
    for (int i = 0; i < 3; i++) {  /* R_D = R R_0^T, t_D = t - R_D t_0 */
        for (int j = 0; j < 3; j++)
            D[4 * i + j] = pose[4 * i] * before[4 * j] + pose[4 * i + 1] * before[4 * j + 1]
                           + pose[4 * i + 2] * before[4 * j + 2];
        D[4 * i + 3] = pose[4 * i + 3] - (D[4 * i] * before[3] + D[4 * i + 1] * before[7] + D[4 * i + 2] * before[11]);
    }
    D[15] = 1.0;
    nlm_log_se3(D, small, near_pi, step);
    nlm_exp_se3(step, small, E);
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 4; j++)
            ahead[4 * i + j] = E[4 * i] * pose[j] + E[4 * i + 1] * pose[4 + j] + E[4 * i + 2] * pose[8 + j]
                               + (j == 3 ? E[4 * i + 3] : 0.0);
    ahead[12] = ahead[13] = ahead[14] = 0.0, ahead[15] = 1.0;
    sizes[0] = sqrt(step[0] * step[0] + step[1] * step[1] + step[2] * step[2]);
    sizes[1] = sqrt(step[3] * step[3] + step[4] * step[4] + step[5] * step[5]);
}
