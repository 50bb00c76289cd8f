// A small linear program, solved by the simplex method on the condensed (Tucker) tableau:
// maximise cost . v subject to a v <= b, v >= 0, with b >= 0 (the origin is feasible).
// kneeseat_core/settle/model.py builds the program (the move that climbs most on the travel's
// first-order model); the climb asks it at every fine step, where a general solver's setup
// alone costs more than the step. Bland's rule: no cycling on the degenerate vertices that
// many equal gaps make.
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <algorithm>
#include <cmath>
#include <cstring>
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

bool get_doubles(PyObject *obj, Py_buffer *view, const char *what) {
    return kneeseat::get_buffer(obj, view, "d", 8, what);
}

// maximise(a (m, n), b (m,), cost (n,)) -> v (n,) as bytes
PyObject *maximise(PyObject *, PyObject *args) {
    PyObject *ao, *bo, *co;
    if (!PyArg_ParseTuple(args, "OOO", &ao, &bo, &co)) return nullptr;
    Py_buffer a, b, c;
    if (!get_doubles(ao, &a, "a")) return nullptr;
    if (!get_doubles(bo, &b, "b")) { PyBuffer_Release(&a); return nullptr; }
    if (!get_doubles(co, &c, "cost")) { PyBuffer_Release(&a); PyBuffer_Release(&b); return nullptr; }
    Py_ssize_t m = b.len / 8, n = c.len / 8;
    const double *pa = static_cast<const double *>(a.buf), *pb = static_cast<const double *>(b.buf),
                 *pc = static_cast<const double *>(c.buf);
    bool ok = n > 0 && a.len == 8 * m * n && m < 1000000 && n < 64;
    for (Py_ssize_t i = 0; ok && i < m; ++i) ok = pb[i] >= 0.0 && std::isfinite(pb[i]);
    for (Py_ssize_t i = 0; ok && i < m * n; ++i) ok = std::isfinite(pa[i]);
    for (Py_ssize_t i = 0; ok && i < n; ++i) ok = std::isfinite(pc[i]);
    if (!ok) {
        PyBuffer_Release(&a); PyBuffer_Release(&b); PyBuffer_Release(&c);
        PyErr_SetString(PyExc_ValueError, "maximise: finite a (m, n), b (m,) >= 0, cost (n,)");
        return nullptr;
    }
    const int w = static_cast<int>(n) + 1;
    std::vector<double> t((m + 1) * w, 0.0), v;
    for (Py_ssize_t i = 0; i < m; ++i) {
        std::memcpy(&t[i * w], pa + i * n, n * sizeof(double));
        t[i * w + n] = pb[i];
    }
    for (Py_ssize_t j = 0; j < n; ++j) t[m * w + j] = -pc[j];
    PyBuffer_Release(&a); PyBuffer_Release(&b); PyBuffer_Release(&c);
    solve(t, static_cast<int>(m), static_cast<int>(n), v);
    return PyBytes_FromStringAndSize(reinterpret_cast<const char *>(v.data()), n * 8);
}

PyMethodDef methods[] = {
    {"maximise", maximise, METH_VARARGS,
     "maximise(a, b, cost) -> v: cost . v largest with a v <= b, v >= 0 (b >= 0)"},
    {nullptr, nullptr, 0, nullptr}};

PyModuleDef module_def = {PyModuleDef_HEAD_INIT, "_simplex",
                          "A small linear program by the simplex method.", -1, methods};

}  // namespace

PyMODINIT_FUNC PyInit__simplex() { return PyModule_Create(&module_def); }
