/* castimate_gn.c: Levenberg-Marquardt / Gauss-Newton solver of a castimate least-squares problem.
 *
 * Part of the code emitted by `castimate codegen PROBLEM.yaml`; this file is the same for every
 * problem. The problem itself (sizes, index tables, priors, unit-norm rows) is in
 * castimate_problem.c, and the residuals and their Jacobians are CasADi-generated functions in
 * castimate_cg.c, emitted from the same symbolic factor functions the Python solve uses.
 *
 * The problem (castimate/solve.py):
 *
 *     minimise 1/2 |r(x)|^2  subject to  |w_row|^2 = 1 for every unit-norm row,
 *
 * with w = [x .* scale; p_fixed] and r the stacked whitened residuals of the factor blocks (each a
 * small function of a few entries of w and a few data) and of the Gaussian priors.
 *
 * Each iteration solves the Gauss-Newton system with Levenberg-Marquardt damping mu,
 *
 *     [J^T J + mu I   A^T] [dx ]     [J^T r]
 *     [A              0  ] [lam] = - [c    ],
 *
 * where A is the Jacobian of the unit-norm constraints c. The variables split into *global* ones
 * (calibration parameters, positions) and *local* blocks (the direction of one static pose; the
 * motion omega, omega_dot, s of one sample) such that every residual involves at most one local
 * block. The matrix is then block-arrow shaped and the local blocks (with their constraints) are
 * eliminated block by block (Schur complement onto the global variables), so the cost of an
 * iteration grows linearly with the number of poses or samples. After a step the unit-norm rows
 * are normalised again (a retraction onto the sphere), so the iterates stay feasible and the fixed
 * point is the constrained optimum IPOPT finds: J^T r + A^T lam = 0, c = 0. A step is accepted if
 * it lowers the cost (then mu shrinks by Nielsen's rule from the ratio of the actual to the predicted
 * decrease), else mu grows; the iteration stops when the largest step
 * component (in the scaled variables x) is below CASTIMATE_XTOL.
 */
#include <math.h>
#include <string.h>
#ifdef CASTIMATE_VERBOSE
#include <stdio.h>
#endif

#include "castimate_cg.h"
#include "castimate_problem.h"
#include "castimate_solver.h"

#define NX CS_NX
#define NW (CS_NX + CS_NP)
#define NG CS_NG
#define NG1 (CS_NG + CS_CG)          /* global unknowns: variables and constraint multipliers */
#define KMAX (CS_LMAX + CS_CMAX)     /* largest local system */
#define ALLOC(n) ((n) > 0 ? (n) : 1) /* C99 has no zero-length arrays */

/* Work space: static, the solver is not reentrant. Sized at generation time. */
static double w_[ALLOC(NW)], w_trial_[ALLOC(NW)];
static double Hgg_[ALLOC(NG1 * NG1)], gg_[ALLOC(NG1)];
static double Hll_[ALLOC(CS_NL * CS_LMAX * CS_LMAX)], gl_[ALLOC(CS_NL * KMAX)];
static double Hlg_[ALLOC(CS_NL * CS_LMAX * NG)];
static double Al_[ALLOC(CS_NL * CS_CMAX * CS_LMAX)], Ag_[ALLOC(CS_CG * NG)];
static double Kl_[ALLOC(CS_NL * KMAX * KMAX)];
static int pivl_[ALLOC(CS_NL * KMAX)], pivg_[ALLOC(NG1)];
static double X_[ALLOC(KMAX * (NG1 + 1))], S_[ALLOC(NG1 * NG1)], rhs_[ALLOC(NG1)];
static double dx_[ALLOC(NX)], dl_[ALLOC(KMAX)];
static int widx_[ALLOC(CS_NWIDX)];

/* Dense LU with partial pivoting of the n x n row-major A, in place. Returns 0, or 1 if singular. */
static int lu(int n, double *A, int *piv)
{
    int i, j, k;
    for (k = 0; k < n; ++k) {
        int p = k;
        double best = fabs(A[k * n + k]);
        for (i = k + 1; i < n; ++i)
            if (fabs(A[i * n + k]) > best) {
                best = fabs(A[i * n + k]);
                p = i;
            }
        piv[k] = p;
        if (!(best > 0.0)) return 1;
        if (p != k)
            for (j = 0; j < n; ++j) {
                double t = A[k * n + j];
                A[k * n + j] = A[p * n + j];
                A[p * n + j] = t;
            }
        for (i = k + 1; i < n; ++i) {
            double f = A[i * n + k] /= A[k * n + k];
            if (f != 0.0)
                for (j = k + 1; j < n; ++j) A[i * n + j] -= f * A[k * n + j];
        }
    }
    return 0;
}

/* Solve with the factors of lu() for m right-hand sides, B row-major n x m with leading dimension ld. */
static void lu_solve(int n, const double *A, const int *piv, double *B, int m, int ld)
{
    int i, j, k;
    for (k = 0; k < n; ++k)
        if (piv[k] != k)
            for (j = 0; j < m; ++j) {
                double t = B[k * ld + j];
                B[k * ld + j] = B[piv[k] * ld + j];
                B[piv[k] * ld + j] = t;
            }
    for (i = 0; i < n; ++i)
        for (k = 0; k < i; ++k) {
            double f = A[i * n + k];
            if (f != 0.0)
                for (j = 0; j < m; ++j) B[i * ld + j] -= f * B[k * ld + j];
        }
    for (i = n - 1; i >= 0; --i) {
        for (k = i + 1; k < n; ++k) {
            double f = A[i * n + k];
            if (f != 0.0)
                for (j = 0; j < m; ++j) B[i * ld + j] -= f * B[k * ld + j];
        }
        for (j = 0; j < m; ++j) B[i * ld + j] /= A[i * n + i];
    }
}

/* Expand the run-length encoded index tables: widx_[block offset + instance * nz + column]. */
static void expand_indices(void)
{
    int b, j, r, t;
    for (b = 0; b < CS_NBLOCK; ++b) {
        const cs_block *B = &cs_blocks[b];
        for (j = 0; j < B->nz; ++j) {
            const int *run = cs_runs + 3 * cs_col_runs[B->col0 + j];
            int nrun = cs_col_runs[B->col0 + j + 1] - cs_col_runs[B->col0 + j];
            t = 0;
            for (r = 0; r < nrun; ++r, run += 3) {
                int k;
                for (k = 0; k < run[2]; ++k, ++t) widx_[B->widx0 + t * B->nz + j] = run[0] + k * run[1];
            }
        }
    }
}

static void set_w(const double *x, const double *p, double *w)
{
    int i;
    for (i = 0; i < NX; ++i) w[i] = x[i] * cs_x_scale[i];
    for (i = 0; i < CS_NP; ++i) w[NX + i] = p[i];
}

/* 1/2 |r|^2 at w. Returns -1 if a residual is not finite. */
static double cost(const double *w, const double *data)
{
    double z[ALLOC(CS_ZMAX)], r[ALLOC(CS_MMAX)], work[ALLOC(CS_SZ_W)];
    casadi_int iw[ALLOC(CS_SZ_IW)];
    const casadi_real *arg[ALLOC(CS_SZ_ARG)];
    casadi_real *res[ALLOC(CS_SZ_RES)];
    double f = 0.0;
    int b, t, j, i;
    for (b = 0; b < CS_NBLOCK; ++b) {
        const cs_block *B = &cs_blocks[b];
        for (t = 0; t < B->n; ++t) {
            const int *wi = widx_ + B->widx0 + t * B->nz;
            for (j = 0; j < B->nz; ++j) z[j] = w[wi[j]];
            arg[0] = z;
            arg[1] = data + B->data0 + t * B->nd;
            res[0] = r;
            B->res(arg, res, iw, work, 0);
            for (i = 0; i < B->m; ++i) f += 0.5 * r[i] * r[i];
        }
    }
    for (i = 0; i < CS_NPRIOR; ++i) {
        double e = (w[cs_prior_x[i]] - cs_prior_mean[i]) / cs_prior_std[i];
        f += 0.5 * e * e;
    }
    return isfinite(f) ? f : -1.0;
}

/* Gauss-Newton system at w: H = J^T J and g = J^T r in the scaled variables x, split into the
 * global block, the local blocks and their coupling; constraint Jacobians and values. */
static double assemble(const double *w, const double *data)
{
    double z[ALLOC(CS_ZMAX)], r[ALLOC(CS_MMAX)], J[ALLOC(CS_MMAX * CS_ZMAX)], work[ALLOC(CS_SZ_W)];
    double *col[ALLOC(CS_ZMAX)], sc[ALLOC(CS_ZMAX)];
    int xi[ALLOC(CS_ZMAX)];
    casadi_int iw[ALLOC(CS_SZ_IW)];
    const casadi_real *arg[ALLOC(CS_SZ_ARG)];
    casadi_real *res[ALLOC(CS_SZ_RES)];
    double f = 0.0;
    int b, t, j, i, a, c, k;
    memset(Hgg_, 0, sizeof Hgg_);
    memset(gg_, 0, sizeof gg_);
    memset(Hll_, 0, sizeof Hll_);
    memset(gl_, 0, sizeof gl_);
    memset(Hlg_, 0, sizeof Hlg_);
    memset(Al_, 0, sizeof Al_);
    memset(Ag_, 0, sizeof Ag_);
    for (b = 0; b < CS_NBLOCK; ++b) {
        const cs_block *B = &cs_blocks[b];
        const int *act = cs_act + B->act0;
        for (t = 0; t < B->n; ++t) {
            const int *wi = widx_ + B->widx0 + t * B->nz;
            int na = 0, loc = -1;
            for (j = 0; j < B->nz; ++j) z[j] = w[wi[j]];
            arg[0] = z;
            arg[1] = data + B->data0 + t * B->nd;
            res[0] = r;
            res[1] = J;
            B->res_jac(arg, res, iw, work, 0);
            for (i = 0; i < B->m; ++i) f += 0.5 * r[i] * r[i];
            /* the free columns of this instance (J is column-major, m x nact) */
            for (j = 0; j < B->nact; ++j) {
                int wj = wi[act[j]];
                if (wj >= NX) continue;
                xi[na] = wj;
                sc[na] = cs_x_scale[wj];
                col[na] = J + j * B->m;
                if (cs_x_local[wj] >= 0) loc = cs_x_local[wj];
                ++na;
            }
            for (a = 0; a < na; ++a) {
                int ia = xi[a], ga = cs_x_global[ia];
                double ga_ = 0.0;
                for (i = 0; i < B->m; ++i) ga_ += col[a][i] * r[i];
                ga_ *= sc[a];
                if (ga >= 0) gg_[ga] += ga_;
                else gl_[loc * KMAX + cs_x_lpos[ia]] += ga_;
                for (c = 0; c < na; ++c) {
                    int ic = xi[c], gc = cs_x_global[ic];
                    double h = 0.0;
                    if (ga >= 0 && gc < 0) continue; /* the transpose of a local-global entry */
                    for (i = 0; i < B->m; ++i) h += col[a][i] * col[c][i];
                    h *= sc[a] * sc[c];
                    if (ga >= 0) Hgg_[ga * NG1 + gc] += h;
                    else if (gc >= 0) Hlg_[(loc * CS_LMAX + cs_x_lpos[ia]) * ALLOC(NG) + gc] += h;
                    else Hll_[(loc * CS_LMAX + cs_x_lpos[ia]) * CS_LMAX + cs_x_lpos[ic]] += h;
                }
            }
        }
    }
    for (i = 0; i < CS_NPRIOR; ++i) {
        int ix = cs_prior_x[i], gi = cs_x_global[ix];
        double s = cs_x_scale[ix] / cs_prior_std[i], e = (w[ix] - cs_prior_mean[i]) / cs_prior_std[i];
        f += 0.5 * e * e;
        if (gi >= 0) {
            Hgg_[gi * NG1 + gi] += s * s;
            gg_[gi] += s * e;
        } else {
            int l = cs_x_local[ix], p = cs_x_lpos[ix];
            Hll_[(l * CS_LMAX + p) * CS_LMAX + p] += s * s;
            gl_[l * KMAX + p] += s * e;
        }
    }
    /* unit-norm constraints c = |w_row|^2 - 1, dc/dx_i = 2 w_i scale_i */
    for (k = 0; k < CS_NUNIT; ++k) {
        const int *row = cs_unit_w + k * CS_UMAX;
        int l = cs_unit_local[k], pos = cs_unit_pos[k];
        double cval = -1.0;
        for (j = 0; j < CS_UMAX && row[j] >= 0; ++j) {
            int wj = row[j];
            cval += w[wj] * w[wj];
            if (wj >= NX) continue;
            if (l >= 0) Al_[(l * CS_CMAX + pos) * CS_LMAX + cs_x_lpos[wj]] = 2.0 * w[wj] * cs_x_scale[wj];
            else Ag_[pos * ALLOC(NG) + cs_x_global[wj]] = 2.0 * w[wj] * cs_x_scale[wj];
        }
        if (l >= 0) gl_[l * KMAX + cs_loc_n[l] + pos] = cval;
        else gg_[NG + pos] = cval;
    }
    return f;
}

/* Marquardt's damping of a diagonal entry: scale invariant, floored for empty rows. */
static double damp(double h)
{
    return h > 1e-12 ? h : 1e-12;
}

/* The damped step dx for damping mu: eliminate the local blocks, solve for the global unknowns,
 * back-substitute. Returns 0, or 1 if a system is singular. */
static int step(double mu)
{
    int l, i, j, k, a;
    /* global system [Hgg + mu I, Ag^T; Ag, 0] and right-hand side -[gg; cg] */
    for (i = 0; i < NG1; ++i) {
        for (j = 0; j < NG1; ++j) {
            double v = 0.0;
            if (i < NG && j < NG) v = Hgg_[i * NG1 + j] + (i == j ? mu * damp(Hgg_[i * NG1 + i]) : 0.0);
            else if (i >= NG && j < NG) v = Ag_[(i - NG) * ALLOC(NG) + j];
            else if (i < NG && j >= NG) v = Ag_[(j - NG) * ALLOC(NG) + i];
            S_[i * NG1 + j] = v;
        }
        rhs_[i] = -gg_[i];
    }
    for (l = 0; l < CS_NL; ++l) {
        int n = cs_loc_n[l], m = n + cs_loc_c[l];
        double *K = Kl_ + l * KMAX * KMAX;
        int *piv = pivl_ + l * KMAX;
        for (i = 0; i < m; ++i)
            for (j = 0; j < m; ++j) {
                double v = 0.0;
                if (i < n && j < n) {
                    v = Hll_[(l * CS_LMAX + i) * CS_LMAX + j];
                    if (i == j) v += mu * damp(v);
                }
                else if (i >= n && j < n) v = Al_[(l * CS_CMAX + i - n) * CS_LMAX + j];
                else if (i < n && j >= n) v = Al_[(l * CS_CMAX + j - n) * CS_LMAX + i];
                K[i * m + j] = v;
            }
        if (lu(m, K, piv)) return 1;
        if (NG == 0) continue;
        /* X = K^-1 [Hlg, gl] (multiplier rows of Hlg are zero); S -= Hlg^T X, rhs += Hlg^T X_g */
        for (i = 0; i < m; ++i) {
            for (j = 0; j < NG; ++j) X_[i * (NG + 1) + j] = i < n ? Hlg_[(l * CS_LMAX + i) * ALLOC(NG) + j] : 0.0;
            X_[i * (NG + 1) + NG] = gl_[l * KMAX + i];
        }
        lu_solve(m, K, piv, X_, NG + 1, NG + 1);
        for (i = 0; i < n; ++i) {
            const double *h = Hlg_ + (l * CS_LMAX + i) * ALLOC(NG);
            const double *xr = X_ + i * (NG + 1);
            for (a = 0; a < NG; ++a) {
                double ha = h[a];
                if (ha == 0.0) continue;
                for (k = a; k < NG; ++k) S_[a * NG1 + k] -= ha * xr[k]; /* upper triangle: S is symmetric */
                rhs_[a] += ha * xr[NG];
            }
        }
    }
    for (a = 0; a < NG; ++a)
        for (k = 0; k < a; ++k) S_[a * NG1 + k] = S_[k * NG1 + a];
    if (NG1 > 0) {
        if (lu(NG1, S_, pivg_)) return 1;
        lu_solve(NG1, S_, pivg_, rhs_, 1, 1);
    }
    for (i = 0; i < NX; ++i)
        if (cs_x_global[i] >= 0) dx_[i] = rhs_[cs_x_global[i]];
    /* local steps: K dl = -(gl + Hlg dg) */
    for (l = 0; l < CS_NL; ++l) {
        int n = cs_loc_n[l], m = n + cs_loc_c[l];
        for (i = 0; i < m; ++i) {
            double v = gl_[l * KMAX + i];
            if (i < n)
                for (j = 0; j < NG; ++j) v += Hlg_[(l * CS_LMAX + i) * ALLOC(NG) + j] * rhs_[j];
            dl_[i] = -v;
        }
        lu_solve(m, Kl_ + l * KMAX * KMAX, pivl_ + l * KMAX, dl_, 1, 1);
        for (i = 0; i < n; ++i) dx_[cs_loc_x[l * CS_LMAX + i]] = dl_[i];
    }
    return 0;
}

/* Put every unit-norm row back on the sphere by scaling its free components. */
static void normalise(double *x, const double *w)
{
    int k, j;
    for (k = 0; k < CS_NUNIT; ++k) {
        const int *row = cs_unit_w + k * CS_UMAX;
        double fixed = 0.0, free = 0.0, s;
        for (j = 0; j < CS_UMAX && row[j] >= 0; ++j) {
            double v = row[j] < NX ? x[row[j]] * cs_x_scale[row[j]] : w[row[j]];
            if (row[j] < NX) free += v * v;
            else fixed += v * v;
        }
        if (!(free > 0.0) || fixed >= 1.0) continue;
        s = sqrt((1.0 - fixed) / free);
        for (j = 0; j < CS_UMAX && row[j] >= 0; ++j)
            if (row[j] < NX) x[row[j]] *= s;
    }
}


/* g^T dx with the gradient of the last assemble(). */
static double gradient_dot_step(void)
{
    double v = 0.0;
    int i;
    for (i = 0; i < NX; ++i)
        v += dx_[i] * (cs_x_global[i] >= 0 ? gg_[cs_x_global[i]] : gl_[cs_x_local[i] * KMAX + cs_x_lpos[i]]);
    return v;
}

static int indices_ready = 0;

int castimate_solve(const double *p_fixed, const double *data, const double *x0, double *x,
                    castimate_solve_info *info)
{
    double f, f_trial, mu = CASTIMATE_MU0, nu = 2.0, dmax, xmax, predicted;
    static double x_trial[ALLOC(NX)];
    int it, i, status = CASTIMATE_MAX_ITER, n_eval = 0;
    if (data == 0 || x == 0) return CASTIMATE_BAD_INPUT;
    if (!indices_ready) {
        expand_indices();
        indices_ready = 1;
    }
    if (p_fixed == 0) p_fixed = cs_p0;
    for (i = 0; i < NX; ++i) x[i] = x0 ? x0[i] : cs_x0[i];
    set_w(x, p_fixed, w_);
    normalise(x, w_);
    set_w(x, p_fixed, w_);
    f = assemble(w_, data);
    if (!isfinite(f)) return CASTIMATE_NOT_FINITE;
    for (it = 0; it < CASTIMATE_MAX_ITERATIONS; ++it) {
        int accepted = 0, tries;
        for (tries = 0; tries < 40 && !accepted; ++tries) {
            if (step(mu)) {
                mu *= 10.0;
                continue;
            }
            dmax = 0.0;
            xmax = 0.0;
            for (i = 0; i < NX; ++i) {
                x_trial[i] = x[i] + dx_[i];
                if (fabs(dx_[i]) > dmax) dmax = fabs(dx_[i]);
                if (fabs(x[i]) > xmax) xmax = fabs(x[i]);
            }
            /* the decrease the linear model predicts: -g^T dx - 1/2 dx^T H dx, which is
             * (-g^T dx + mu dx^T D dx) / 2 >= -g^T dx / 2 for the damped step */
            predicted = -0.5 * gradient_dot_step();
            set_w(x_trial, p_fixed, w_trial_);
            normalise(x_trial, w_trial_);
            set_w(x_trial, p_fixed, w_trial_);
            f_trial = cost(w_trial_, data);
            ++n_eval;
#ifdef CASTIMATE_VERBOSE
            fprintf(stderr, "iteration %d: mu %.3e, max |dx| %.3e, predicted %.3e, cost %.15g -> %.15g\n", it, mu,
                    dmax, predicted, f, f_trial);
#endif
            /* Accept a step that lowers the cost, or one whose predicted decrease is below the
             * round-off of the cost (there the cost cannot rank steps any more). */
            if (f_trial >= 0.0 && (f_trial < f || predicted <= CASTIMATE_FTOL * f)) {
                /* Nielsen's update from the gain ratio rho = actual / predicted decrease */
                /* (in the round-off regime the ratio means nothing: shrink as for a perfect model) */
                double rho = predicted > CASTIMATE_FTOL * f ? (f - f_trial) / predicted : 1.0, t = 2.0 * rho - 1.0;
                double shrink = 1.0 - t * t * t;
                accepted = dmax <= CASTIMATE_XTOL * (1.0 + xmax) ? 2 : 1;
                memcpy(x, x_trial, sizeof(double) * NX);
                f = f_trial;
                mu *= shrink > 1.0 / 3.0 ? shrink : 1.0 / 3.0;
                if (mu < 1e-15) mu = 1e-15;
                nu = 2.0;
            } else {
                mu *= nu;
                nu *= 2.0;
            }
        }
        if (!accepted) {
            status = CASTIMATE_STALLED;
            break;
        }
        set_w(x, p_fixed, w_);
        f = assemble(w_, data);
        if (accepted == 2) {
            status = CASTIMATE_CONVERGED;
            ++it;
            break;
        }
    }
    if (info) {
        info->iterations = it;
        info->cost_evaluations = n_eval;
        info->cost = f;
        info->status = status;
    }
    return status;
}

void castimate_values(const double *p_fixed, const double *x, double *values)
{
    int i;
    if (p_fixed == 0) p_fixed = cs_p0;
    set_w(x, p_fixed, w_);
    for (i = 0; i < CS_NVAL; ++i) values[i] = w_[cs_value_w[i]];
}

void castimate_x_from_values(const double *values, double *x)
{
    int i;
    for (i = 0; i < CS_NVAL; ++i)
        if (cs_value_w[i] < NX) x[cs_value_w[i]] = values[i] / cs_x_scale[cs_value_w[i]];
}
