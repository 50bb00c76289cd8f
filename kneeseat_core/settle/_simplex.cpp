// A small linear program, solved by the simplex method on the condensed (Tucker) tableau:
// maximise cost . v subject to a v <= b, v >= 0, with b >= 0 (the origin is feasible).
// `best_move` builds the program kneeseat_core/settle/model.py asks (the move that climbs
// most on the travel's first-order model) and solves it: the climb asks it at every fine
// step, where a general solver's setup alone costs more than the step. Bland's rule: no
// cycling on the degenerate vertices that many equal gaps make.
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <algorithm>
#include <cmath>
#include <vector>

#include "../_buffers.h"

namespace {

constexpr int kMaxPivots = 200;     // far more than a few columns need; a cap against a bad tableau
constexpr double kPivot = 1e-9;     // a pivot smaller than this is rounding
constexpr double kReduced = 1e-12;  // a reduced cost below this (relative) is zero

// t: (m + 1) x (n + 1) row-major, the last row the objective, the last column b
void solve(std::vector<double> &t, int m, int n, std::vector<double> &v) {
    const int w = n + 1;
    std::vector<int> col_var(n), row_var(m);
    for (int j = 0; j < n; ++j) col_var[j] = j;
    for (int i = 0; i < m; ++i) row_var[i] = n + i;
    double scale = 1.0;
    for (int j = 0; j < n; ++j) scale = std::max(scale, std::fabs(t[m * w + j]));
    std::vector<double> pivot_row(w), col(m + 1);
    for (int it = 0; it < kMaxPivots; ++it) {
        int s = -1;                                   // entering: the lowest variable
        for (int j = 0; j < n; ++j)
            if (t[m * w + j] < -kReduced * scale && (s < 0 || col_var[j] < col_var[s])) s = j;
        if (s < 0) break;
        double least = INFINITY;                      // leaving: least ratio...
        for (int i = 0; i < m; ++i)
            if (t[i * w + s] > kPivot) least = std::min(least, t[i * w + n] / t[i * w + s]);
        int r = -1;                                   // ...its lowest variable among ties
        double tie = 1e-12 * std::max(1.0, std::fabs(least));
        for (int i = 0; i < m && std::isfinite(least); ++i)
            if (t[i * w + s] > kPivot && t[i * w + n] / t[i * w + s] <= least + tie &&
                (r < 0 || row_var[i] < row_var[r]))
                r = i;
        if (r < 0) break;                             // unbounded: stop where it is
        double p = t[r * w + s];
        for (int j = 0; j < w; ++j) pivot_row[j] = t[r * w + j] / p;
        for (int i = 0; i <= m; ++i) col[i] = t[i * w + s];
        for (int i = 0; i <= m; ++i) {
            if (i == r || col[i] == 0.0) continue;
            double f = col[i];
            for (int j = 0; j < w; ++j) t[i * w + j] -= f * pivot_row[j];
        }
        for (int j = 0; j < w; ++j) t[r * w + j] = pivot_row[j];
        for (int i = 0; i <= m; ++i) t[i * w + s] = -col[i] / p;
        t[r * w + s] = 1.0 / p;
        std::swap(col_var[s], row_var[r]);
    }
    v.assign(n, 0.0);
    for (int i = 0; i < m; ++i)
        if (row_var[i] < n) v[row_var[i]] = t[i * w + n];
}

// A slope below a nanometre per metre is rounding (a pivot on it would blow the tableau up).
constexpr double kFlatSlope = 1e-9;
// The cost of a move per unit of its length, relative to the objective's own rates.
constexpr double kStill = 1e-6;
constexpr double kEps = 1e-12;

bool get_doubles(PyObject *obj, Py_buffer *view, const char *what) {
    return kneeseat::get_buffer(obj, view, "d", 8, what, PyExc_ValueError);
}

// best_move(gaps (k,), slopes (k, 3), press, drive (3,), radius (3,)) -> (x (3,) as bytes,
// promised): the move x with |x_i| <= radius_i that maximises press s(x) + drive . x under
// the model s(x) = min_k (gaps_k + slopes_k . x), and what that promises over no move
// (measured on the model itself: a rounding in the tableau can promise what the box does
// not hold). Columns of the program: x+ (3), x- (3), s - lowest (1), all >= 0, the origin
// (no move) feasible; a move that gains nothing is not made (each unit of its length
// costs a millionth of the rates), so a direction the model holds level (a slide along a
// groove) stays at no move instead of running to the box's corner.
PyObject *best_move(PyObject *, PyObject *args) {
    PyObject *go, *so, *dobj, *ro;
    double press;
    if (!PyArg_ParseTuple(args, "OOdOO", &go, &so, &press, &dobj, &ro)) return nullptr;
    Py_buffer b[4];
    int held = 0;
    bool ok = get_doubles(go, &b[0], "gaps") && ++held && get_doubles(so, &b[1], "slopes") && ++held &&
              get_doubles(dobj, &b[2], "drive") && ++held && get_doubles(ro, &b[3], "radius") && ++held;
    const Py_ssize_t k = ok ? b[0].len / 8 : 0;
    ok = ok && k > 0 && b[1].len == 24 * k && b[2].len == 24 && b[3].len == 24 && std::isfinite(press);
    const double *gaps = ok ? static_cast<const double *>(b[0].buf) : nullptr;
    const double *drive = ok ? static_cast<const double *>(b[2].buf) : nullptr;
    const double *radius = ok ? static_cast<const double *>(b[3].buf) : nullptr;
    std::vector<double> slopes(ok ? 3 * k : 0);
    for (Py_ssize_t i = 0; ok && i < 3 * k; ++i) {
        double a = static_cast<const double *>(b[1].buf)[i];
        ok = std::isfinite(a);
        slopes[i] = std::fabs(a) < kFlatSlope ? 0.0 : a;
    }
    for (Py_ssize_t i = 0; ok && i < k; ++i) ok = std::isfinite(gaps[i]);
    for (int i = 0; ok && i < 3; ++i) ok = std::isfinite(drive[i]) && radius[i] >= 0.0 && std::isfinite(radius[i]);
    if (!ok) {
        for (int i = 0; i < held; ++i) PyBuffer_Release(&b[i]);
        if (!PyErr_Occurred())
            PyErr_SetString(PyExc_ValueError, "best_move: finite gaps (k,) with k > 0, slopes (k, 3), press, "
                                              "drive (3,) and radius (3,) >= 0");
        return nullptr;
    }
    double floor = INFINITY, lowest = INFINITY;
    for (Py_ssize_t j = 0; j < k; ++j) {
        const double *a = &slopes[3 * j];
        floor = std::min(floor, gaps[j]);
        lowest = std::min(lowest, gaps[j] - (std::fabs(a[0]) * radius[0] + std::fabs(a[1]) * radius[1] +
                                             std::fabs(a[2]) * radius[2]));
    }
    lowest -= kEps;                    // the least travel any move in the box can model
    const int m = static_cast<int>(k) + 6, n = 7, w = n + 1;
    std::vector<double> t((m + 1) * w, 0.0), v;
    for (Py_ssize_t j = 0; j < k; ++j) {
        double *row = &t[j * w];
        for (int i = 0; i < 3; ++i) {
            row[i] = -slopes[3 * j + i];
            row[3 + i] = slopes[3 * j + i];
        }
        row[6] = 1.0;
        row[n] = gaps[j] - lowest;
    }
    for (int i = 0; i < 3; ++i) {
        t[(k + i) * w + i] = t[(k + 3 + i) * w + 3 + i] = 1.0;
        t[(k + i) * w + n] = t[(k + 3 + i) * w + n] = radius[i];
    }
    double still = std::fabs(press);
    for (int i = 0; i < 3; ++i) still = std::max(still, std::fabs(drive[i]));
    still *= kStill;
    double *objective = &t[m * w];      // the last row holds -cost
    for (int i = 0; i < 3; ++i) {
        objective[i] = -(drive[i] - still);
        objective[3 + i] = -(-drive[i] - still);
    }
    objective[6] = -press;
    solve(t, m, n, v);
    double x[3];
    for (int i = 0; i < 3; ++i) x[i] = std::min(std::max(v[i] - v[3 + i], -radius[i]), radius[i]);
    double travel = INFINITY;
    for (Py_ssize_t j = 0; j < k; ++j) {
        const double *a = &slopes[3 * j];
        travel = std::min(travel, gaps[j] + (a[0] * x[0] + a[1] * x[1] + a[2] * x[2]));
    }
    const double promised = press * (travel - floor) + (drive[0] * x[0] + drive[1] * x[1] + drive[2] * x[2]);
    for (int i = 0; i < held; ++i) PyBuffer_Release(&b[i]);
    return Py_BuildValue("(Nd)", PyBytes_FromStringAndSize(reinterpret_cast<const char *>(x), 24), promised);
}

PyMethodDef methods[] = {
    {"best_move", best_move, METH_VARARGS,
     "best_move(gaps, slopes, press, drive, radius) -> (x, promised): the move the model says climbs most"},
    {nullptr, nullptr, 0, nullptr}};

PyModuleDef module_def = {PyModuleDef_HEAD_INIT, "_simplex",
                          "The move that climbs most on a first-order model: a small linear program by the simplex method.", -1, methods};

}  // namespace

PyMODINIT_FUNC PyInit__simplex() { return PyModule_Create(&module_def); }
