// The climb's arithmetic around the exact travel (kneeseat_core/settle/planner.py is its
// Python face; kneeseat_core/settle/climb.py asks it at every step and pose): the moves a
// step tries, planned at once (the order the near-active features' first-order model
// promises, each move's pose - a slide across the push and a spin about the axis through
// the body's centroid parallel to it - and the travel along the push each must reach to
// gain: one Newton step of the lift), what a pose at contact is worth, the objective's
// first-order terms, and the travel's first-order model about a pose from its features;
// the ligaments weighed at every pose (_tissue.h). A step considers up to 27 moves of a
// few arrays each; numpy's calls on arrays that small cost several times their arithmetic.
//
// The pose of a move x = (slide e1, slide e2, arc): R = I + sin(a) K + (1 - cos(a)) K^2
// with K the push's cross-product matrix and a = arc / arm, the body turned by R about its
// centroid c and slid by x0 e1 + x1 e2. The objective at a pose is, per unit load, the
// load's work (l . c along a fixed line, -|o - c| toward a point o) less the ligaments'
// energy, or the depth along the push for the travel alone. The lift: from no
// lift its rate is l . push - dE/ds / F (l the load's line), and the lift that gains is
// (want - value) / rate where the rate is positive (none otherwise: inf). The objective is
// concave along the push, so the step lifts no higher than needed.
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <numeric>
#include <vector>

#include "../_buffers.h"
#include "../_feature.h"
#include "../_tissue.h"

namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();

struct Planner {
    double push[3], e1[3], e2[3], free[3], centroid[3];
    double arm = 1.0, standoff = 0.0, load_n = 1.0;
    double steepest = 3.0;       // a feature whose slope is steeper is left out of models
    double k[9], k2[9];          // the push's cross-product matrix K and K @ K
    bool work = false;           // the objective is the load's work less the energy
    bool toward = false;         // the load pulls toward a point (else along the push)
    double point[3] = {0.0, 0.0, 0.0};
    bool tissue = false;
    kneeseat::Fibres fibres;

    // the pose (16,) of `base` moved by `move` (3,)
    void lateral(const double *base, const double *move, double *out) const;
    // what the pose is worth (the objective per unit load: the load's work less the
    // ligaments' energy, or the depth along the push for the travel alone); with `rate`,
    // also the objective's rate under a lift along the push
    double worth(const double *pose, double *rate = nullptr);
    // the travel along the push the pose `target` must reach for the objective to be `want`
    double lift(const double *target, double want);
    // the objective's first-order terms at `pose`: a move x (slide e1, slide e2, arc) that
    // changes the travel by dt changes it by press dt + drive . x; `pull` the ligaments'
    // rate along the push per unit load (dE/ds / F), `line` the load's (l . push)
    void first_order(const double *pose, double &press, double *drive, double &pull, double &line);
};

void Planner::lateral(const double *base, const double *move, double *out) const {
    const double x0 = move[0] * free[0], x1 = move[1] * free[1], x2 = move[2] * free[2];
    const double a = x2 / arm, s = std::sin(a), c = std::cos(a);
    double r[9];
    for (int i = 0; i < 9; ++i) r[i] = ((i % 4 == 0 ? 1.0 : 0.0) + s * k[i]) + (1.0 - c) * k2[i];
    double centre[3], rel[3];
    for (int i = 0; i < 3; ++i) {
        centre[i] = base[4 * i] * centroid[0] + base[4 * i + 1] * centroid[1] + base[4 * i + 2] * centroid[2] +
                    base[4 * i + 3];
        rel[i] = base[4 * i + 3] - centre[i];
    }
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j)
            out[4 * i + j] = r[3 * i] * base[j] + r[3 * i + 1] * base[4 + j] + r[3 * i + 2] * base[8 + j];
        out[4 * i + 3] = (r[3 * i] * rel[0] + r[3 * i + 1] * rel[1] + r[3 * i + 2] * rel[2]) + centre[i] +
                         (x0 * e1[i] + x1 * e2[i]);
    }
    out[12] = out[13] = out[14] = 0.0;
    out[15] = 1.0;
}

double Planner::worth(const double *pose, double *rate) {
    if (!work) {
        if (rate) *rate = 1.0;
        return pose[3] * push[0] + pose[7] * push[1] + pose[11] * push[2];
    }
    double energy = 0.0, force[3] = {0.0, 0.0, 0.0};
    if (tissue) energy = fibres.push(pose, force);
    double centre[3];
    for (int i = 0; i < 3; ++i)
        centre[i] = pose[4 * i] * centroid[0] + pose[4 * i + 1] * centroid[1] + pose[4 * i + 2] * centroid[2] +
                    pose[4 * i + 3];
    double value, line_push;
    if (toward) {
        double d[3] = {point[0] - centre[0], point[1] - centre[1], point[2] - centre[2]};
        double length = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
        value = -length;
        line_push = (d[0] * push[0] + d[1] * push[1] + d[2] * push[2]) / length;
    } else {
        value = centre[0] * push[0] + centre[1] * push[1] + centre[2] * push[2];
        line_push = 1.0;
    }
    if (rate) *rate = line_push - (force[0] * push[0] + force[1] * push[1] + force[2] * push[2]) / load_n;
    return value - energy / load_n;
}

double Planner::lift(const double *target, double want) {
    double slope;
    const double value = worth(target, &slope);
    return slope > 0.0 ? (want - value) / slope : kInf;
}

void Planner::first_order(const double *pose, double &press, double *drive, double &pull, double &line) {
    pull = 0.0;
    line = 1.0;
    drive[0] = drive[1] = drive[2] = 0.0;
    if (!work) {
        press = 1.0;
        return;
    }
    double centre[3], l[3] = {push[0], push[1], push[2]};
    for (int i = 0; i < 3; ++i)
        centre[i] = pose[4 * i] * centroid[0] + pose[4 * i + 1] * centroid[1] + pose[4 * i + 2] * centroid[2] +
                    pose[4 * i + 3];
    if (toward) {
        double d[3] = {point[0] - centre[0], point[1] - centre[1], point[2] - centre[2]};
        double length = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
        for (int i = 0; i < 3; ++i) l[i] = d[i] / length;
    }
    double lateral[3] = {0.0, 0.0, 0.0};
    if (tissue) {
        double force[3], torque[3];
        fibres.push(pose, force, torque);
        // the spin turns the body about the axis through its centroid along the push, one
        // radian per arm of arc: its rate is the moment about the centroid along the push
        const double about_centre = push[0] * (centre[1] * force[2] - centre[2] * force[1]) +
                                    push[1] * (centre[2] * force[0] - centre[0] * force[2]) +
                                    push[2] * (centre[0] * force[1] - centre[1] * force[0]);
        const double moment = (torque[0] * push[0] + torque[1] * push[1] + torque[2] * push[2] - about_centre) / arm;
        pull = (force[0] * push[0] + force[1] * push[1] + force[2] * push[2]) / load_n;
        lateral[0] = (force[0] * e1[0] + force[1] * e1[1] + force[2] * e1[2]) / load_n;
        lateral[1] = (force[0] * e2[0] + force[1] * e2[1] + force[2] * e2[2]) / load_n;
        lateral[2] = moment / load_n;
    }
    line = l[0] * push[0] + l[1] * push[1] + l[2] * push[2];
    press = line - pull;
    drive[0] = (l[0] * e1[0] + l[1] * e1[1] + l[2] * e1[2]) - lateral[0];
    drive[1] = (l[0] * e2[0] + l[1] * e2[1] + l[2] * e2[2]) - lateral[1];
    drive[2] = -lateral[2];
}

// ---- Python -----------------------------------------------------------------------------

struct PyPlanner {
    PyObject_HEAD
    Planner *planner;
};

PyTypeObject PlannerType = {PyVarObject_HEAD_INIT(nullptr, 0)};

// `count` doubles of `obj` into `out` (a C-contiguous float64 buffer of exactly that many)
bool read_doubles(PyObject *obj, Py_ssize_t count, double *out, const char *what) {
    Py_buffer b;
    if (!kneeseat::get_buffer(obj, &b, "d", 8, what, PyExc_ValueError)) return false;
    bool ok = b.len == 8 * count;
    if (ok) std::copy_n(static_cast<const double *>(b.buf), count, out);
    else PyErr_Format(PyExc_ValueError, "Planner: %s has the wrong shape", what);
    PyBuffer_Release(&b);
    return ok;
}

// a whole C-contiguous buffer of 8-byte `format` items into `out`
template <class T>
bool read_all(PyObject *obj, const char *format, std::vector<T> &out, const char *what) {
    Py_buffer b;
    if (!kneeseat::get_buffer(obj, &b, format, 8, what, PyExc_ValueError)) return false;
    const T *p = static_cast<const T *>(b.buf);
    out.assign(p, p + b.len / 8);
    PyBuffer_Release(&b);
    return true;
}

void planner_dealloc(PyPlanner *self) {
    delete self->planner;
    Py_TYPE(self)->tp_free(reinterpret_cast<PyObject *>(self));
}

// Planner(push, e1, e2, free, centroid, arm, standoff, steepest, work, load_n, toward|None,
// fibres|None)
// fibres: (seg_local (s, 3), seg_sign (s,), seg_fixed (s, 3), seg_fibre (s,) int64, slack
// (f,), stiffness (f,), transition (f,))
int planner_init(PyPlanner *self, PyObject *args, PyObject *) {
    PyObject *po, *ao, *bo, *fo, *co, *to, *so;
    double arm, standoff, steepest, load_n;
    int work;
    if (!PyArg_ParseTuple(args, "OOOOOdddpdOO", &po, &ao, &bo, &fo, &co, &arm, &standoff, &steepest, &work, &load_n,
                          &to, &so))
        return -1;
    auto *p = new Planner();
    bool ok = read_doubles(po, 3, p->push, "push") && read_doubles(ao, 3, p->e1, "e1") &&
              read_doubles(bo, 3, p->e2, "e2") && read_doubles(fo, 3, p->free, "free") &&
              read_doubles(co, 3, p->centroid, "centroid");
    p->arm = arm;
    p->standoff = standoff;
    p->steepest = steepest;
    p->work = work;
    p->load_n = load_n;
    if (ok && !(arm > 0.0 && load_n > 0.0 && standoff >= 0.0 && steepest > 0.0)) {
        PyErr_SetString(PyExc_ValueError, "Planner: arm, load and steepest positive, standoff not negative");
        ok = false;
    }
    if (ok && to != Py_None) {
        p->toward = true;
        ok = read_doubles(to, 3, p->point, "toward");
    }
    if (ok && so != Py_None) {
        kneeseat::Fibres &t = p->fibres;
        PyObject *parts[7];
        ok = PyArg_ParseTuple(so, "OOOOOOO", &parts[0], &parts[1], &parts[2], &parts[3], &parts[4], &parts[5],
                              &parts[6]) &&
             read_all(parts[0], "d", t.local, "seg_local") && read_all(parts[1], "d", t.sign, "seg_sign") &&
             read_all(parts[2], "d", t.fixed, "seg_fixed") && read_all(parts[3], "q", t.fibre, "seg_fibre") &&
             read_all(parts[4], "d", t.slack, "slack") && read_all(parts[5], "d", t.stiffness, "stiffness") &&
             read_all(parts[6], "d", t.transition, "transition");
        const size_t s = t.segments(), f = t.fibres();
        ok = ok && t.local.size() == 3 * s && t.fixed.size() == 3 * s && t.fibre.size() == s &&
             t.stiffness.size() == f && t.transition.size() == f;
        for (size_t i = 0; ok && i < s; ++i) ok = t.fibre[i] >= 0 && static_cast<size_t>(t.fibre[i]) < f;
        if (!ok && !PyErr_Occurred())
            PyErr_SetString(PyExc_ValueError, "Planner: fibres of segments (s, 3), (s,), (s, 3), fibres (s,) "
                                              "indexing slack, stiffness and transition (f,)");
        p->tissue = true;
    }
    if (!ok) {
        delete p;
        return -1;
    }
    const double x = p->push[0], y = p->push[1], z = p->push[2];
    const double k[9] = {0.0, -z, y, z, 0.0, -x, -y, x, 0.0};
    std::copy_n(k, 9, p->k);
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            p->k2[3 * i + j] = k[3 * i] * k[j] + k[3 * i + 1] * k[3 + j] + k[3 * i + 2] * k[6 + j];
    delete self->planner;
    self->planner = p;
    return 0;
}

// a held buffer of doubles: `what`, a multiple of `unit` doubles long (count set)
bool take_rows(PyObject *obj, Py_buffer &b, Py_ssize_t unit, Py_ssize_t &count, const char *what) {
    if (!kneeseat::get_buffer(obj, &b, "d", 8, what, PyExc_ValueError)) return false;
    count = b.len / (8 * unit);
    if (b.len == 8 * unit * count) return true;
    PyErr_Format(PyExc_ValueError, "Planner: %s has the wrong shape", what);
    PyBuffer_Release(&b);
    return false;
}

// bytes of `size` from `data` (empty where there is nothing: a vector's data may be null)
PyObject *bytes_of(const void *data, Py_ssize_t size) {
    return PyBytes_FromStringAndSize(size ? static_cast<const char *>(data) : "", size);
}

bool ready(PyPlanner *self) {
    if (self->planner) return true;
    PyErr_SetString(PyExc_ValueError, "Planner: not initialised");
    return false;
}

// laterals(base (4, 4), moves (m, 3)) -> poses (m, 4, 4) as bytes
PyObject *planner_laterals(PyPlanner *self, PyObject *args) {
    PyObject *bo, *mo;
    if (!ready(self) || !PyArg_ParseTuple(args, "OO", &bo, &mo)) return nullptr;
    double base[16];
    Py_buffer mb;
    Py_ssize_t m;
    if (!read_doubles(bo, 16, base, "base") || !take_rows(mo, mb, 3, m, "moves")) return nullptr;
    std::vector<double> out(16 * m);
    const double *moves = static_cast<const double *>(mb.buf);
    for (Py_ssize_t i = 0; i < m; ++i) self->planner->lateral(base, moves + 3 * i, &out[16 * i]);
    PyBuffer_Release(&mb);
    return bytes_of(out.data(), 128 * m);
}

// plan(base (4, 4), moves (m, 3), gaps (k,), slopes (k, 3), press, drive (3,), tries, gain,
// want) -> (order (t,) int64, targets (t, 4, 4), needed (t,)) as bytes: the first `tries`
// moves (all when negative) most promising first (press (s(x) - min gaps) + drive . x, the
// model s(x) = min_k (gaps_k + slopes_k . x); ties in the order given), their poses and
// the travel each must reach to gain (the lift that brings the objective to `want`, or
// `gain` for the travel alone, plus the standoff)
PyObject *planner_plan(PyPlanner *self, PyObject *args) {
    PyObject *bo, *mo, *go, *so, *dobj;
    double press, gain, want;
    Py_ssize_t tries;
    if (!ready(self) || !PyArg_ParseTuple(args, "OOOOdOndd", &bo, &mo, &go, &so, &press, &dobj, &tries, &gain, &want))
        return nullptr;
    Planner &p = *self->planner;
    double base[16], drive[3];
    if (!read_doubles(bo, 16, base, "base") || !read_doubles(dobj, 3, drive, "drive")) return nullptr;
    Py_buffer b[3];
    Py_ssize_t m, k, k3;
    if (!take_rows(mo, b[0], 3, m, "moves")) return nullptr;
    if (!take_rows(go, b[1], 1, k, "gaps")) { PyBuffer_Release(&b[0]); return nullptr; }
    bool held = take_rows(so, b[2], 3, k3, "slopes");
    if (!held || k3 != k) {
        if (held) {
            PyBuffer_Release(&b[2]);
            PyErr_SetString(PyExc_ValueError, "Planner: slopes (k, 3) for gaps (k,)");
        }
        PyBuffer_Release(&b[0]);
        PyBuffer_Release(&b[1]);
        return nullptr;
    }
    const double *moves = static_cast<const double *>(b[0].buf), *gaps = static_cast<const double *>(b[1].buf),
                 *slopes = static_cast<const double *>(b[2].buf);
    std::vector<double> promise(m);
    double floor = kInf;
    for (Py_ssize_t j = 0; j < k; ++j) floor = std::min(floor, gaps[j]);
    for (Py_ssize_t i = 0; i < m; ++i) {
        const double *x = moves + 3 * i;
        double v = x[0] * drive[0] + x[1] * drive[1] + x[2] * drive[2];
        if (k > 0) {
            double travel = kInf;
            for (Py_ssize_t j = 0; j < k; ++j) {
                const double *a = slopes + 3 * j;
                travel = std::min(travel, gaps[j] + (x[0] * a[0] + x[1] * a[1] + x[2] * a[2]));
            }
            v += press * (travel - floor);
        }
        promise[i] = v;
    }
    std::vector<int64_t> order(m);
    std::iota(order.begin(), order.end(), 0);
    std::stable_sort(order.begin(), order.end(), [&](int64_t a, int64_t c) { return promise[a] > promise[c]; });
    const Py_ssize_t t = tries < 0 ? m : std::min(tries, m);
    order.resize(t);
    std::vector<double> targets(16 * t), needed(t);
    for (Py_ssize_t i = 0; i < t; ++i) {
        double *target = &targets[16 * i];
        p.lateral(base, moves + 3 * order[i], target);
        needed[i] = (p.work ? p.lift(target, want) : gain) + p.standoff;
    }
    for (auto &buf : b) PyBuffer_Release(&buf);
    return Py_BuildValue("(NNN)", bytes_of(order.data(), 8 * t), bytes_of(targets.data(), 128 * t),
                         bytes_of(needed.data(), 8 * t));
}

// model(features, rise, centre (3,), within, room) -> (gaps, slopes (k', 3), faces (k', 2)
// int64) as bytes: the travel's first-order model about a pose from its features
// (kneeseat_core/settle/model.py; the engine's records, _feature.h, measured from the pose
// `rise` short of it along the push: each gap is that much less from the pose, each point
// that much further along the push): those closing within `within` that hold for a slide
// of at least `room` (all of those within, where none does) and are not steeper than
// `steepest`. A feature with unit normal n (n . push >= 0) at the moving body's point p
// changes its gap by -n . dp / n . push under a move that moves p by dp: dp = x0 e1 + x1
// e2 + x2 (push x (p - c)) / arm for the move x (c the centroid, the spin's axis through
// it), so its slopes over x are -(n . e1, n . e2, n . (push x (p - c)) / arm) / n . push, a
// locked move's zero; one whose slope exceeds `steepest` in any coordinate holds for a
// sliver of a move (a crossing of two edges nearly parallel seen along the push, a triangle
// seen edge on) and is left out.
PyObject *planner_model(PyPlanner *self, PyObject *args) {
    PyObject *fo, *co;
    double rise, within, room;
    if (!ready(self) || !PyArg_ParseTuple(args, "OdOdd", &fo, &rise, &co, &within, &room)) return nullptr;
    const Planner &p = *self->planner;
    double centre[3];
    if (!read_doubles(co, 3, centre, "centre")) return nullptr;
    Py_buffer b;
    if (PyObject_GetBuffer(fo, &b, PyBUF_C_CONTIGUOUS) < 0) return nullptr;
    if (b.len % static_cast<Py_ssize_t>(sizeof(kneeseat::Feature)) != 0) {
        PyBuffer_Release(&b);
        PyErr_SetString(PyExc_ValueError, "Planner.model: features must be whole feature records");
        return nullptr;
    }
    const Py_ssize_t k = b.len / static_cast<Py_ssize_t>(sizeof(kneeseat::Feature));
    const kneeseat::Feature *features = static_cast<const kneeseat::Feature *>(b.buf);
    // a feature that holds for the room if any within does
    bool roomy = false;
    for (Py_ssize_t j = 0; j < k && !roomy; ++j)
        roomy = features[j].gap - rise <= within && features[j].room >= room;
    std::vector<double> out_gaps, out_slopes;
    std::vector<int64_t> out_faces;
    for (Py_ssize_t j = 0; j < k; ++j) {
        const kneeseat::Feature &f = features[j];
        const double gap = f.gap - rise;
        if (!(gap <= within) || (roomy && !(f.room >= room))) continue;
        const double *n = f.normal;
        const double q[3] = {f.point[0] + rise * p.push[0], f.point[1] + rise * p.push[1],
                             f.point[2] + rise * p.push[2]};
        const double d[3] = {q[0] - centre[0], q[1] - centre[1], q[2] - centre[2]};
        const double lever[3] = {(p.push[1] * d[2] - p.push[2] * d[1]) / p.arm,
                                 (p.push[2] * d[0] - p.push[0] * d[2]) / p.arm,
                                 (p.push[0] * d[1] - p.push[1] * d[0]) / p.arm};
        const double along = n[0] * p.push[0] + n[1] * p.push[1] + n[2] * p.push[2];
        const double across[3] = {(n[0] * p.e1[0] + n[1] * p.e1[1] + n[2] * p.e1[2]) * p.free[0],
                                  (n[0] * p.e2[0] + n[1] * p.e2[1] + n[2] * p.e2[2]) * p.free[1],
                                  (n[0] * lever[0] + n[1] * lever[1] + n[2] * lever[2]) * p.free[2]};
        const double steepest = std::max({std::fabs(across[0]), std::fabs(across[1]), std::fabs(across[2])});
        if (!(steepest <= p.steepest * along)) continue;
        out_gaps.push_back(gap);
        for (int i = 0; i < 3; ++i) out_slopes.push_back(-across[i] / along);
        out_faces.push_back(f.moving_face);
        out_faces.push_back(f.fixed_face);
    }
    PyBuffer_Release(&b);
    const Py_ssize_t kept = static_cast<Py_ssize_t>(out_gaps.size());
    return Py_BuildValue("(NNN)", bytes_of(out_gaps.data(), 8 * kept), bytes_of(out_slopes.data(), 24 * kept),
                         bytes_of(out_faces.data(), 16 * kept));
}

// first_order(pose (4, 4)) -> (press, drive (3,) as bytes, pull, line) (Planner::first_order)
PyObject *planner_first_order(PyPlanner *self, PyObject *args) {
    PyObject *po;
    double pose[16];
    if (!ready(self) || !PyArg_ParseTuple(args, "O", &po) || !read_doubles(po, 16, pose, "pose")) return nullptr;
    double press, drive[3], pull, line;
    self->planner->first_order(pose, press, drive, pull, line);
    return Py_BuildValue("(dNdd)", press, bytes_of(drive, 24), pull, line);
}

// value(pose (4, 4)) -> what the pose is worth (Planner::worth)
PyObject *planner_value(PyPlanner *self, PyObject *args) {
    PyObject *po;
    double pose[16];
    if (!ready(self) || !PyArg_ParseTuple(args, "O", &po) || !read_doubles(po, 16, pose, "pose")) return nullptr;
    return PyFloat_FromDouble(self->planner->worth(pose));
}

// pushes(poses (m, 4, 4)) -> (energies (m,), dE/dt (m, 3)) as bytes: the ligaments weighed
// as the lifts weigh them (zero without ligaments)
PyObject *planner_pushes(PyPlanner *self, PyObject *args) {
    PyObject *po;
    if (!ready(self) || !PyArg_ParseTuple(args, "O", &po)) return nullptr;
    Py_buffer b;
    Py_ssize_t m;
    if (!take_rows(po, b, 16, m, "poses")) return nullptr;
    std::vector<double> energies(m, 0.0), forces(3 * m, 0.0);
    const double *poses = static_cast<const double *>(b.buf);
    if (self->planner->tissue)
        for (Py_ssize_t i = 0; i < m; ++i) energies[i] = self->planner->fibres.push(poses + 16 * i, &forces[3 * i]);
    PyBuffer_Release(&b);
    return Py_BuildValue("(NN)", bytes_of(energies.data(), 8 * m), bytes_of(forces.data(), 24 * m));
}

PyMethodDef planner_methods[] = {
    {"laterals", reinterpret_cast<PyCFunction>(planner_laterals), METH_VARARGS,
     "laterals(base, moves) -> poses: base moved by each lateral move"},
    {"plan", reinterpret_cast<PyCFunction>(planner_plan), METH_VARARGS,
     "plan(base, moves, gaps, slopes, press, drive, tries, gain, want) -> (order, targets, needed)"},
    {"model", reinterpret_cast<PyCFunction>(planner_model), METH_VARARGS,
     "model(features, rise, centre, within, room) -> (gaps, slopes, faces)"},
    {"first_order", reinterpret_cast<PyCFunction>(planner_first_order), METH_VARARGS,
     "first_order(pose) -> (press, drive, pull, line): the objective's first-order terms"},
    {"value", reinterpret_cast<PyCFunction>(planner_value), METH_VARARGS,
     "value(pose) -> what the pose is worth: the objective per unit load"},
    {"pushes", reinterpret_cast<PyCFunction>(planner_pushes), METH_VARARGS,
     "pushes(poses) -> (energies, forces): the ligaments at each pose"},
    {nullptr, nullptr, 0, nullptr}};

PyModuleDef module_def = {PyModuleDef_HEAD_INIT, "_moves", "The climb's arithmetic around the exact travel.", -1,
                          nullptr};

}  // namespace

PyMODINIT_FUNC PyInit__moves() {
    PlannerType.tp_name = "kneeseat_core.settle._moves.Planner";
    PlannerType.tp_doc = "Planner(push, e1, e2, free, centroid, arm, standoff, steepest, work, load_n, toward, fibres)";
    PlannerType.tp_basicsize = sizeof(PyPlanner);
    PlannerType.tp_flags = Py_TPFLAGS_DEFAULT;
    PlannerType.tp_new = PyType_GenericNew;
    PlannerType.tp_init = reinterpret_cast<initproc>(planner_init);
    PlannerType.tp_dealloc = reinterpret_cast<destructor>(planner_dealloc);
    PlannerType.tp_methods = planner_methods;
    if (PyType_Ready(&PlannerType) < 0) return nullptr;
    PyObject *m = PyModule_Create(&module_def);
    if (!m) return nullptr;
    Py_INCREF(&PlannerType);
    if (PyModule_AddObject(m, "Planner", reinterpret_cast<PyObject *>(&PlannerType)) < 0) {
        Py_DECREF(m);
        return nullptr;
    }
    return m;
}
