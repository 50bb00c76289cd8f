// The ligaments' energy and its rates under a translation and a rotation at a pose of one
// body (kneeseat_core/ligaments.py, `Tissue`, defines them with numpy; settle/_moves.cpp
// weighs every pose a climb considers with this).
//
// Each segment's vector is seg_local turned by the pose, plus seg_sign times the pose's
// translation, plus seg_fixed; a fibre's length is the sum of its segments'; the force law
// (Blankevoort 1991) with m the strain clipped to [0, e_t] and l what lies above e_t is
// f = k (m^2 / (2 e_t) + l) and E / L0 = k (m^3 / (6 e_t) + m l / 2 + l^2 / 2).
#ifndef KNEESEAT_TISSUE_H
#define KNEESEAT_TISSUE_H

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace kneeseat {

// One body's fibres: s segments of f fibres (arrays as in ligaments.Tissue), owned.
struct Fibres {
    std::vector<double> local, sign, fixed, slack, stiffness, transition;   // (s, 3) (s,) (s, 3) (f,) x3
    std::vector<int64_t> fibre;                                              // (s,) in [0, f)
    // scratch of one evaluation
    std::vector<double> vec, length, total, tension;

    size_t segments() const { return sign.size(); }
    size_t fibres() const { return slack.size(); }

    // The energy and dE/dt (3,) at a (4, 4) pose; with `torque`, dE/dθ (3,) too for a small
    // rotation θ about the reference frame's origin (the sum over segments of the moving
    // end's position, moving_s = the segment's vector less its fixed part, crossed with the
    // segment's pull).
    double push(const double *pose, double *force, double *torque = nullptr) {
        const size_t s = segments(), f = fibres();
        vec.resize(3 * s);
        length.resize(s);
        total.assign(f, 0.0);
        tension.resize(f);
        for (size_t i = 0; i < s; ++i) {
            const double *q = &local[3 * i];
            double *v = &vec[3 * i];
            for (int r = 0; r < 3; ++r)
                v[r] = pose[4 * r] * q[0] + pose[4 * r + 1] * q[1] + pose[4 * r + 2] * q[2] +
                       sign[i] * pose[4 * r + 3] + fixed[3 * i + r];
            length[i] = std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
            total[fibre[i]] += length[i];
        }
        double energy = 0.0;
        for (size_t j = 0; j < f; ++j) {
            double e = std::max(total[j] / slack[j] - 1.0, 0.0);
            double toe_strain = std::min(e, transition[j]), over = e - toe_strain;
            double toe = toe_strain * toe_strain / (2.0 * transition[j]);
            tension[j] = stiffness[j] * (toe + over);
            energy += stiffness[j] * (toe_strain * toe / 3.0 + over * (0.5 * toe_strain + 0.5 * over)) * slack[j];
        }
        force[0] = force[1] = force[2] = 0.0;
        for (size_t i = 0; i < s; ++i) {
            double scale = sign[i] * tension[fibre[i]] / std::max(length[i], 1e-12);
            for (int r = 0; r < 3; ++r) force[r] += scale * vec[3 * i + r];
        }
        if (torque) {
            torque[0] = torque[1] = torque[2] = 0.0;
            for (size_t i = 0; i < s; ++i) {
                const double *v = &vec[3 * i], *f = &fixed[3 * i];
                const double scale = tension[fibre[i]] / std::max(length[i], 1e-12);
                const double p[3] = {scale * v[0], scale * v[1], scale * v[2]};
                const double q[3] = {v[0] - f[0], v[1] - f[1], v[2] - f[2]};
                torque[0] += q[1] * p[2] - q[2] * p[1];
                torque[1] += q[2] * p[0] - q[0] * p[2];
                torque[2] += q[0] * p[1] - q[1] * p[0];
            }
        }
        return energy;
    }
};

}  // namespace kneeseat

#endif
