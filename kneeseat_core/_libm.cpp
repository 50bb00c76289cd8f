// The C library's elementary functions applied to every element of an array of doubles
// (kneeseat_core/libm.py is its Python face). Each element goes through the same libm call
// Python's `math` module makes (sin, cos, exp, log, log1p, pow), so the bits are the same as
// `math.f(x)` element by element; a loop here spares the interpreter's round trip per element,
// which made the embedded knee's first synthesis spend most of its time in them. Compiled
// without -ffast-math, GCC calls the scalar functions one by one: no vector variant (libmvec),
// whose last bits differ, is ever chosen.
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <cmath>
#include <cstring>

#include "_buffers.h"

namespace {

enum Kind { kSin, kCos, kExp, kLog, kLog1p, kPow };

double apply(int kind, double x, double p) {
    switch (kind) {
        case kSin: return sin(x);
        case kCos: return cos(x);
        case kExp: return exp(x);
        case kLog: return log(x);
        case kLog1p: return x == 0.0 ? x : log1p(x);   // as Python's math.log1p
        default: return pow(x, p);
    }
}

// elementwise(kind, x, p) -> bytes: f(x) of every double of x (p: pow's exponent)
PyObject *elementwise(PyObject *, PyObject *args) {
    const char *name;
    PyObject *xo;
    double p = 0.0;
    if (!PyArg_ParseTuple(args, "sO|d", &name, &xo, &p)) return nullptr;
    static const char *const names[] = {"sin", "cos", "exp", "log", "log1p", "pow"};
    int kind = -1;
    for (int k = 0; k <= kPow; ++k)
        if (std::strcmp(name, names[k]) == 0) kind = k;
    if (kind < 0) {
        PyErr_Format(PyExc_ValueError, "elementwise: unknown function '%s' (one of sin, cos, "
                     "exp, log, log1p, pow)", name);
        return nullptr;
    }
    Py_buffer x;
    if (!kneeseat::get_buffer(xo, &x, "d", 8, "elementwise: x")) return nullptr;
    Py_ssize_t n = x.len / 8;
    PyObject *out = PyBytes_FromStringAndSize(nullptr, n * 8);
    if (out == nullptr) {
        PyBuffer_Release(&x);
        return nullptr;
    }
    const double *in = static_cast<const double *>(x.buf);
    double *y = reinterpret_cast<double *>(PyBytes_AS_STRING(out));
    Py_ssize_t bad = -1;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < n; ++i) {
        y[i] = apply(kind, in[i], p);
        // Python's math raises where a finite argument has no finite value
        if (bad < 0 && !std::isfinite(y[i]) && std::isfinite(in[i])) bad = i;
    }
    Py_END_ALLOW_THREADS
    if (bad >= 0) {
        PyObject *value = PyFloat_FromDouble(in[bad]);
        if (value != nullptr) {
            PyErr_Format(PyExc_ValueError, "%s(%R) has no finite value (a math domain or "
                         "range error)", name, value);
            Py_DECREF(value);
        }
        PyBuffer_Release(&x);
        Py_DECREF(out);
        return nullptr;
    }
    PyBuffer_Release(&x);
    return out;
}

PyMethodDef methods[] = {
    {"elementwise", elementwise, METH_VARARGS,
     "elementwise(name, x, p=0.0) -> bytes: the C library's name(x) (pow: x ** p) of every "
     "double of the C-contiguous buffer x, bit for bit Python's math.name element by element"},
    {nullptr, nullptr, 0, nullptr}};

PyModuleDef module_def = {PyModuleDef_HEAD_INIT, "_libm",
                          "The C library's elementary functions of arrays of doubles.", -1,
                          methods};

}  // namespace

PyMODINIT_FUNC PyInit__libm() { return PyModule_Create(&module_def); }
