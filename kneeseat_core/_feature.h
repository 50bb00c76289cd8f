// One contact feature of the exact travel, as the engine (meshes/_sweep.cpp) finds it and
// the planner (settle/_moves.cpp) reads it: kneeseat_core/meshes/sweep.py's `FEATURE` is the
// same record for numpy.
#ifndef KNEESEAT_FEATURE_H
#define KNEESEAT_FEATURE_H

#include <cstdint>

namespace kneeseat {

struct Feature {
    double gap;            // along the push, from the pose measured
    double normal[3];      // unit, n . push >= 0
    double point[3];       // the moving body's point at the feature, fixed frame
    double room;           // how far a slide keeps the feature one
    int64_t kind;          // 0: moving vertex on fixed face, 1: the reverse, 2: edges
    int64_t moving_face, fixed_face;
};

static_assert(sizeof(Feature) == 88, "the record numpy reads (meshes/sweep.py, FEATURE)");

}  // namespace kneeseat

#endif
