// The ligaments' energy and its rate under a translation at many poses of one body at once
// (kneeseat_core/ligaments.py, `Tissue.pushes_many`): the climb weighs every move it
// considers by how far the body must be lifted along the push for the move to gain, and
// on a few dozen poses of a hundred segments numpy's stacked arrays cost three times the
// arithmetic. The same quantities as `Tissue.rates` (its energy and dE/dt), to rounding.
//
// Each segment's vector is seg_local turned by the pose, plus seg_sign times the pose's
// translation, plus seg_fixed; a fibre's length is the sum of its segments'; the force law
// (Blankevoort 1991) with m the strain clipped to [0, e_t] and l what lies above e_t is
// f = k (m^2 / (2 e_t) + l) and E / L0 = k (m^3 / (6 e_t) + m l / 2 + l^2 / 2).
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

#include "_buffers.h"

namespace {

// a C-contiguous buffer of `count` 8-byte items of `format` ("d" or "q"; count < 0: any),
// else a ValueError set
bool take(PyObject *obj, Py_buffer &view, const char *format, Py_ssize_t count, const char *what) {
    if (!kneeseat::get_buffer(obj, &view, format, 8, what, PyExc_ValueError)) return false;
    if (count < 0 || view.len == 8 * count) return true;
    PyErr_Format(PyExc_ValueError, "pushes: %s has the wrong shape", what);
    PyBuffer_Release(&view);
    return false;
}

// pushes(seg_local (s, 3), seg_sign (s,), seg_fixed (s, 3), seg_fibre (s,) int64, slack (f,),
// stiffness (f,), transition (f,), poses (m, 4, 4)) -> (energies (m,), dE/dt (m, 3)) as bytes
PyObject *pushes(PyObject *, PyObject *args) {
    PyObject *objs[8];
    if (!PyArg_ParseTuple(args, "OOOOOOOO", &objs[0], &objs[1], &objs[2], &objs[3], &objs[4], &objs[5],
                          &objs[6], &objs[7]))
        return nullptr;
    Py_buffer b[8];
    int held = 0;
    Py_ssize_t s = -1, f = -1, m = -1;
    bool ok = take(objs[1], b[0], "d", -1, "seg_sign") && ++held;
    if (ok) s = b[0].len / 8;
    ok = ok && take(objs[0], b[1], "d", 3 * s, "seg_local") && ++held;
    ok = ok && take(objs[2], b[2], "d", 3 * s, "seg_fixed") && ++held;
    ok = ok && take(objs[3], b[3], "q", s, "seg_fibre") && ++held;
    ok = ok && take(objs[4], b[4], "d", -1, "slack") && ++held;
    if (ok) f = b[4].len / 8;
    ok = ok && take(objs[5], b[5], "d", f, "stiffness") && ++held;
    ok = ok && take(objs[6], b[6], "d", f, "transition") && ++held;
    ok = ok && take(objs[7], b[7], "d", -1, "poses") && ++held;
    if (ok) {
        m = b[7].len / 128;
        const int64_t *fibre = static_cast<const int64_t *>(b[3].buf);
        ok = b[7].len == 128 * m;
        for (Py_ssize_t i = 0; ok && i < s; ++i) ok = fibre[i] >= 0 && fibre[i] < f;
        if (!ok) PyErr_SetString(PyExc_ValueError, "pushes: poses (m, 4, 4) and fibres indexing slack");
    }
    if (!ok) {
        for (int i = 0; i < held; ++i) PyBuffer_Release(&b[i]);
        return nullptr;
    }
    const double *sign = static_cast<const double *>(b[0].buf), *local = static_cast<const double *>(b[1].buf),
                 *fixed = static_cast<const double *>(b[2].buf), *slack = static_cast<const double *>(b[4].buf),
                 *stiffness = static_cast<const double *>(b[5].buf),
                 *transition = static_cast<const double *>(b[6].buf), *poses = static_cast<const double *>(b[7].buf);
    const int64_t *fibre = static_cast<const int64_t *>(b[3].buf);
    std::vector<double> energies(m), forces(3 * m), vec(3 * s), length(s), total(f), tension(f);
    for (Py_ssize_t p = 0; p < m; ++p) {
        const double *pose = poses + 16 * p;
        std::fill(total.begin(), total.end(), 0.0);
        for (Py_ssize_t i = 0; i < s; ++i) {
            const double *q = local + 3 * i;
            double *v = &vec[3 * i];
            for (int r = 0; r < 3; ++r)
                v[r] = pose[4 * r] * q[0] + pose[4 * r + 1] * q[1] + pose[4 * r + 2] * q[2] +
                       sign[i] * pose[4 * r + 3] + fixed[3 * i + r];
            length[i] = std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
            total[fibre[i]] += length[i];
        }
        double energy = 0.0;
        for (Py_ssize_t j = 0; j < f; ++j) {
            double e = std::max(total[j] / slack[j] - 1.0, 0.0);
            double toe_strain = std::min(e, transition[j]), over = e - toe_strain;
            double toe = toe_strain * toe_strain / (2.0 * transition[j]);
            tension[j] = stiffness[j] * (toe + over);
            energy += stiffness[j] * (toe_strain * toe / 3.0 + over * (0.5 * toe_strain + 0.5 * over)) * slack[j];
        }
        double *out = &forces[3 * p];
        out[0] = out[1] = out[2] = 0.0;
        for (Py_ssize_t i = 0; i < s; ++i) {
            double scale = sign[i] * tension[fibre[i]] / std::max(length[i], 1e-12);
            for (int r = 0; r < 3; ++r) out[r] += scale * vec[3 * i + r];
        }
        energies[p] = energy;
    }
    for (int i = 0; i < held; ++i) PyBuffer_Release(&b[i]);
    static const char nothing = 0;         // no poses: empty bytes (a null pointer is None)
    return Py_BuildValue("(y#y#)", m ? reinterpret_cast<const char *>(energies.data()) : &nothing, m * 8,
                         m ? reinterpret_cast<const char *>(forces.data()) : &nothing, m * 24);
}

PyMethodDef module_methods[] = {
    {"pushes", pushes, METH_VARARGS,
     "pushes(seg_local, seg_sign, seg_fixed, seg_fibre, slack, stiffness, transition, poses) -> (energies, forces)"},
    {nullptr, nullptr, 0, nullptr}};

PyModuleDef module_def = {PyModuleDef_HEAD_INIT, "_tissue",
                          "The ligaments' energy and its rate under translation at many poses.", -1,
                          module_methods};

}  // namespace

PyMODINIT_FUNC PyInit__tissue() { return PyModule_Create(&module_def); }
