/* The nonlinear estimator's compiled solve: what its two files share (nlcompiled.py
 * packs nl_model to this layout: its LAYOUT and the sizes exported in _nlsolve.c).
 * _nlmodel.c: the forward model (fluxmodel.py), its Jacobian, SE(3) exp and log
 * (se3.py); _nlsolve.c: the fit (nonlinear.py's _solve). Units SI (T, m, rad);
 * poses 4x4 row-major. */
#ifndef FTSENSORD_NLSOLVE_H
#define FTSENSORD_NLSOLVE_H

#include <stddef.h>

#define NMAX 16         /* chips a sensor may have: the ring has 8 */
#define CMAX (3 * NMAX) /* flux channels */
#define PI 3.141592653589793 /* math.pi */
#define PMAX 9          /* unknowns: the pose's 6 and the background field's 3 */

/* nonlinear.py's tunables, in this order: the enum and the names the loader checks
 * (nl_tunable_index; nlcompiled._tunables packs them by these names) come from this list. */
#define NL_TUNABLES(X) \
    X(MAX_STEP_M) X(MAX_STEP_RAD) X(STEP_TOL) X(STEP_TOL_RAD) X(CONTRACTION) X(REUSE_M) X(REUSE_TRACE) \
    X(REUSE_T) X(MAX_RESIDUAL_T) X(BACKGROUND_LIMIT_T) X(PRIOR_WEIGHT) X(LINEAR_STEP_T) X(UNDAMPED) \
    X(SMALL_ANGLE) X(NEAR_PI) X(MAX_ITERATIONS)
#define NL_ENUM(name) name,
enum { NL_TUNABLES(NL_ENUM) NTUNABLES };
#undef NL_ENUM

/* The model and the estimator's constants, all doubles (nlcompiled.LAYOUT packs it; the
 * loader checks each field's offset against nl_model_offset). */
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

void nlm_predict(const nl_model *M, const double *T, const double *u, double *out);
void nlm_predict_and_jacobian(const nl_model *M, const double *T, const double *u, double *out, double J[][PMAX]);
void nlm_exp_se3(const double *xi, double small, double *E);
void nlm_log_se3(const double *T, double small, double near_pi, double *xi);

#endif
