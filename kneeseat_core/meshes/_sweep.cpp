// The travel along a direction measured exactly: how far a moving triangle mesh can be
// translated along a unit direction d before it first touches a fixed one, and the contact
// features at that first touch (kneeseat_core/meshes/sweep.py is its Python face).
//
// Two triangles translated towards each other along d first touch at a vertex of one on the
// face of the other or at an edge of one across an edge of the other. Seen along d both are
// flat: over the overlap of their shadows the gap along d between them is affine, so its
// least value lies at a corner of that overlap, and every corner is one of those features:
// a vertex of either triangle inside the other's shadow, or two edges whose shadows cross.
// `PairGap` evaluates all fifteen, exactly, in double precision. The same corners give
// the largest gap: a pair whose least and largest gaps have opposite signs crosses already.
//
// Which pairs to evaluate comes from a bounding volume hierarchy over each body (built once,
// in its own frame, `Body`). Seen along a direction (`View`, one per direction, filled as
// it is asked) a node of the hierarchy is bounded by its shadow's rectangle and by a plane
// over it: every point of its triangles lies between two offsets of that plane. Two
// conforming surfaces (a knee's bearing surfaces) have nearly parallel planes, so the gap
// between two nodes is bounded within the nodes' curvature, not within their extent along d
// as axis-aligned boxes would be. The pairs of nodes are opened depth first, the one with the
// lower bound first, and a pair whose bound lies beyond the best contact found (and the
// window past it) is never opened.
//
// Only the triangles facing the other body can take part in a first touch between closed
// bodies (a ray from outside enters through a front face): a View keeps those (`side`), and
// keeps every triangle of a surface that is not closed (an open cartilage sheet has no
// inside, both its faces can be met).
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <memory>
#include <utility>
#include <vector>

#include "../_buffers.h"
#include "../_feature.h"

namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr int kLeafTriangles = 2;     // triangles per leaf of the hierarchy
// Nodes over at most this many triangles get plane bounds from their own vertices; larger
// ones (the top of the tree, asked rarely) are bounded by their box's corners.
constexpr int kPlaneBoundTriangles = 64;

inline double dot3(const double *a, const double *b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
inline double cross2(double ax, double ay, double bx, double by) { return ax * by - ay * bx; }

// A node of the hierarchy as the traversal reads it: twelve bytes, so that a node and its
// first child (the next one) usually share a cache line; its box is kept apart (`Box`),
// read only where a view bounds a large node by it.
struct Node {
    int32_t right;            // second child (the first is the next node); -1 for a leaf
    int32_t first, count;     // the node's triangles: [first, first + count) in tree order
};

struct Box {
    double lo[3], hi[3];      // a node's bounding box, the body's frame
};

struct ViewBuffers;

// One triangle mesh and its hierarchy, in the body's own frame.
struct Body {
    std::vector<double> vertices;    // (n, 3)
    std::vector<int32_t> faces;      // (m, 3) in tree order
    std::vector<int64_t> face_id;    // (m,) index of each face as given
    std::vector<int32_t> tree_index; // (m,) where each face as given sits in tree order
    std::vector<double> normals;     // (m, 3) unit face normals (winding)
    std::vector<double> areas;       // (m,)
    std::vector<int8_t> facing;      // (m,) +1/-1: the outward side of a closed surface
                                     // (winding or its reverse); 0: open, both sides count
    std::vector<Node> nodes;
    std::vector<Box> boxes;          // each node's (`Node`)
    // the distinct vertices of each node bounded by planes (CSR: node i's are
    // node_vertices[node_vertex_start[i], node_vertex_start[i + 1]); none for a larger one)
    std::vector<int32_t> node_vertex_start, node_vertices;
    // the arrays of views of it that are gone, for the next ones (`View`)
    mutable std::vector<ViewBuffers> spare;
    // queries placed on views of it so far: a moving node's bound placed is marked with its
    // query's number, which no view's arrays (spare ones included) hold from before, so
    // they need no clearing (64 bits: it never wraps)
    mutable uint64_t queries = 0;

    int build(std::vector<int32_t> &order, const std::vector<double> &centres, int first, int count);
};

int Body::build(std::vector<int32_t> &order, const std::vector<double> &centres, int first,
                int count) {
    int index = static_cast<int>(nodes.size());
    nodes.push_back(Node{-1, first, count});
    boxes.push_back(Box{{kInf, kInf, kInf}, {-kInf, -kInf, -kInf}});
    if (count <= kLeafTriangles) return index;
    double lo[3] = {kInf, kInf, kInf}, hi[3] = {-kInf, -kInf, -kInf};
    for (int i = first; i < first + count; ++i)
        for (int k = 0; k < 3; ++k) {
            lo[k] = std::min(lo[k], centres[3 * order[i] + k]);
            hi[k] = std::max(hi[k], centres[3 * order[i] + k]);
        }
    int axis = 0;
    for (int k = 1; k < 3; ++k)
        if (hi[k] - lo[k] > hi[axis] - lo[axis]) axis = k;
    int middle = first + count / 2;
    std::nth_element(order.begin() + first, order.begin() + middle, order.begin() + first + count,
                     [&](int32_t a, int32_t b) {
                         return centres[3 * a + axis] < centres[3 * b + axis] ||
                                (centres[3 * a + axis] == centres[3 * b + axis] && a < b);
                     });
    build(order, centres, first, middle - first);
    int right = build(order, centres, middle, first + count - middle);
    nodes[index].right = right;
    return index;
}

void make_body(Body &body, const double *vertices, Py_ssize_t nv, const int64_t *faces,
               Py_ssize_t nf, const int8_t *facing) {
    body.vertices.assign(vertices, vertices + 3 * nv);
    std::vector<double> centres(3 * nf);
    for (Py_ssize_t t = 0; t < nf; ++t)
        for (int k = 0; k < 3; ++k)
            centres[3 * t + k] = (vertices[3 * faces[3 * t] + k] + vertices[3 * faces[3 * t + 1] + k] +
                                  vertices[3 * faces[3 * t + 2] + k]) / 3.0;
    std::vector<int32_t> order(nf);
    for (Py_ssize_t t = 0; t < nf; ++t) order[t] = static_cast<int32_t>(t);
    body.nodes.reserve(2 * nf / kLeafTriangles + 2);
    body.boxes.reserve(2 * nf / kLeafTriangles + 2);
    if (nf > 0) body.build(order, centres, 0, static_cast<int>(nf));
    body.faces.resize(3 * nf);
    body.face_id.resize(nf);
    body.tree_index.resize(nf);
    body.normals.resize(3 * nf);
    body.areas.resize(nf);
    body.facing.resize(nf);
    for (Py_ssize_t i = 0; i < nf; ++i) {
        int64_t t = order[i];
        for (int c = 0; c < 3; ++c) body.faces[3 * i + c] = static_cast<int32_t>(faces[3 * t + c]);
        body.face_id[i] = t;
        body.tree_index[t] = static_cast<int32_t>(i);
        body.facing[i] = facing[t];
        const double *a = &vertices[3 * faces[3 * t]], *b = &vertices[3 * faces[3 * t + 1]],
                     *c = &vertices[3 * faces[3 * t + 2]];
        double e1[3] = {b[0] - a[0], b[1] - a[1], b[2] - a[2]};
        double e2[3] = {c[0] - a[0], c[1] - a[1], c[2] - a[2]};
        double n[3] = {e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2],
                       e1[0] * e2[1] - e1[1] * e2[0]};
        double length = std::sqrt(dot3(n, n));
        body.areas[i] = 0.5 * length;
        for (int k = 0; k < 3; ++k) body.normals[3 * i + k] = length > 0.0 ? n[k] / length : 0.0;
    }
    for (size_t index = 0; index < body.nodes.size(); ++index) {
        const Node &node = body.nodes[index];
        Box &box = body.boxes[index];
        for (int i = node.first; i < node.first + node.count; ++i)
            for (int c = 0; c < 3; ++c) {
                const double *p = &body.vertices[3 * body.faces[3 * i + c]];
                for (int k = 0; k < 3; ++k) {
                    box.lo[k] = std::min(box.lo[k], p[k]);
                    box.hi[k] = std::max(box.hi[k], p[k]);
                }
            }
    }
    // a view bounds such a node over its vertices (View::fill): each once, not once for
    // every triangle that shares it (about four times fewer)
    body.node_vertex_start.assign(1, 0);
    std::vector<int32_t> corners;
    for (const Node &node : body.nodes) {
        if (node.count <= kPlaneBoundTriangles) {
            corners.assign(body.faces.begin() + 3 * node.first,
                           body.faces.begin() + 3 * (node.first + node.count));
            std::sort(corners.begin(), corners.end());
            corners.erase(std::unique(corners.begin(), corners.end()), corners.end());
            body.node_vertices.insert(body.node_vertices.end(), corners.begin(), corners.end());
        }
        body.node_vertex_start.push_back(static_cast<int32_t>(body.node_vertices.size()));
    }
}

// A node seen along d: its shadow's rectangle in (u, w) and a plane h = g . q + c over it
// (c folded into the offsets), every point of its triangles at a height h - g . q in
// [low, high]. low > high: no triangle of the node takes part.
struct alignas(64) Bound {     // one cache line each
    double lo[2], hi[2], g[2], low, high;
};

// A moving node's bound placed for the current query, in the fixed view: its shadow's
// rectangle as a centre and half sides (x, y, rx, ry), its plane h = g . q + c and the
// heights about that plane [low, high] (low > high: no triangle of it takes part).
struct Placed {
    double x, y, rx, ry, g[2], c, low, high;
    double width;             // its shadow's width in its own view (the traversal's choice)
    uint64_t stamp;           // the query it was placed for (`Body::queries`)
};

// The traversal's small steps are forced inline (a node pair's bounds, a vertex's shadow,
// a moving vertex placed): GCC left them as calls, and inline the total knee slice's
// searches took 4 % less time, the same answers bit for bit (benchmarks/engine_ab.py).
#define KNEESEAT_INLINE __attribute__((always_inline)) inline

// What a view of a body fills as it is asked, never cleared beforehand: a flag or a stamp
// says what holds a value.
struct ViewBuffers {
    std::unique_ptr<double[]> shadow;  // (n, 3): u, w, h of each vertex
    std::vector<uint8_t> has_shadow;
    std::unique_ptr<Bound[]> bounds;
    std::vector<uint8_t> has_bound;
    // the moving body's vertices and node bounds placed for the current query (fixed view
    // coordinates; a moving view's), each marked when computed: a vertex with the view's
    // count of queries (`placed_stamp`), a node bound with the body's (`Placed::stamp`)
    std::unique_ptr<double[]> placed;
    std::vector<uint32_t> placed_stamp;
    std::unique_ptr<Placed[]> placed_bounds;
    // each triangle's slope (`slope`), 0 not yet asked, 1 kept, 2 none to trust
    std::unique_ptr<double[]> slopes;
    std::vector<uint8_t> has_slope;
};

// How many sets of a body's view arrays are kept for its next views. A sweep makes a fixed
// view per cell (the push turns with the attitude in the fixed body's frame): a new view of
// the total knee's femoral component took 88 us to allocate its arrays (megabytes) and
// clear their flags, 8 us with a gone view's arrays, whose flags alone are cleared.
constexpr size_t kSpareViews = 2;

// A body seen along a direction d (its own frame): heights along d, shadows in the plane
// across it (basis u, w), and the bounds of its nodes, each computed when first asked.
// `side` +1 (a moving body's view) also places its vertices and node bounds per query.
struct View : ViewBuffers {
    const Body *body;
    double d[3], u[3], w[3];
    int side;                          // +1: the faces whose outside faces +d take part

    View(const Body &b, const double *direction, int side_);
    ~View();
    View(const View &) = delete;
    View &operator=(const View &) = delete;
    const double *vertex(int32_t i);
    const double *slope(int32_t t);
    bool takes_part(int32_t t) const;
    KNEESEAT_INLINE const Bound &bound(int node) {
        if (__builtin_expect(!has_bound[node], 0)) fill(node);
        return bounds[node];
    }
    void fill(int node);   // computes the node's bound, once
};

void across(const double d[3], double u[3], double w[3]) {
    double a[3] = {1.0, 0.0, 0.0};
    if (std::fabs(d[0]) > 0.6) { a[0] = 0.0; a[1] = 1.0; }
    double along = dot3(a, d);
    for (int k = 0; k < 3; ++k) u[k] = a[k] - along * d[k];
    double length = std::sqrt(dot3(u, u));
    for (int k = 0; k < 3; ++k) u[k] /= length;
    w[0] = d[1] * u[2] - d[2] * u[1];
    w[1] = d[2] * u[0] - d[0] * u[2];
    w[2] = d[0] * u[1] - d[1] * u[0];
}

View::View(const Body &b, const double *direction, int side_) : body(&b), side(side_) {
    for (int k = 0; k < 3; ++k) d[k] = direction[k];
    across(d, u, w);
    size_t nv = b.vertices.size() / 3, nn = b.nodes.size(), nt = b.faces.size() / 3;
    if (!b.spare.empty()) {            // a gone view's arrays, their flags cleared
        static_cast<ViewBuffers &>(*this) = std::move(b.spare.back());
        b.spare.pop_back();
    } else {
        shadow.reset(new double[3 * nv]);
        bounds.reset(new Bound[nn]);
        slopes.reset(new double[2 * nt]);
    }
    has_shadow.assign(nv, 0);
    has_bound.assign(nn, 0);
    has_slope.assign(nt, 0);
    if (side == 1) {
        if (!placed) {
            placed.reset(new double[3 * nv]);
            placed_bounds.reset(new Placed[nn]());      // stamps 0: no query's
        }
        placed_stamp.assign(nv + 1, 0);
    }
}

View::~View() {
    if (body->spare.size() < kSpareViews) body->spare.push_back(std::move(static_cast<ViewBuffers &>(*this)));
}

KNEESEAT_INLINE const double *View::vertex(int32_t i) {
    if (!has_shadow[i]) {
        const double *p = &body->vertices[3 * i];
        shadow[3 * i] = dot3(p, u);
        shadow[3 * i + 1] = dot3(p, w);
        shadow[3 * i + 2] = dot3(p, d);
        has_shadow[i] = 1;
    }
    return &shadow[3 * i];
}

// The slope (gx, gy) of triangle t's height over its shadow: its plane is
// h = h0 + gx (u - u0) + gy (w - w0) through any of its vertices (u0, w0, h0). None
// (nullptr) where the shadow is a sliver or the plane steep to d, which would make the
// slope's rounding matter.
KNEESEAT_INLINE const double *View::slope(int32_t t) {
    uint8_t &known = has_slope[t];
    double *g = &slopes[2 * t];
    if (__builtin_expect(known == 0, 0)) {
        const int32_t *f = &body->faces[3 * t];
        const double *p0 = vertex(f[0]), *p1 = vertex(f[1]), *p2 = vertex(f[2]);
        double e1x = p1[0] - p0[0], e1y = p1[1] - p0[1], e1h = p1[2] - p0[2];
        double e2x = p2[0] - p0[0], e2y = p2[1] - p0[1], e2h = p2[2] - p0[2];
        double area = cross2(e1x, e1y, e2x, e2y);
        known = 2;
        if (std::fabs(area) > 1e-3 * (e1x * e1x + e1y * e1y + e2x * e2x + e2y * e2y)) {
            g[0] = (e1h * e2y - e2h * e1y) / area;
            g[1] = (e1x * e2h - e2x * e1h) / area;
            if (std::fabs(g[0]) + std::fabs(g[1]) <= 16.0) known = 1;
        }
    }
    return known == 1 ? g : nullptr;
}

bool View::takes_part(int32_t t) const {
    int8_t facing = body->facing[t];
    return facing == 0 || side * facing * dot3(&body->normals[3 * t], d) >= 0.0;
}

__attribute__((noinline)) void View::fill(int index) {
    has_bound[index] = 1;
    Bound &b = bounds[index];
    const Node &node = body->nodes[index];
    b.lo[0] = b.lo[1] = kInf;
    b.hi[0] = b.hi[1] = -kInf;
    b.g[0] = b.g[1] = 0.0;
    b.low = kInf;
    b.high = -kInf;
    if (node.count > kPlaneBoundTriangles) {      // the box's corners
        const Box &box = body->boxes[index];
        for (int c = 0; c < 8; ++c) {
            double p[3] = {c & 1 ? box.hi[0] : box.lo[0], c & 2 ? box.hi[1] : box.lo[1],
                           c & 4 ? box.hi[2] : box.lo[2]};
            double x = dot3(p, u), y = dot3(p, w), h = dot3(p, d);
            b.lo[0] = std::min(b.lo[0], x); b.hi[0] = std::max(b.hi[0], x);
            b.lo[1] = std::min(b.lo[1], y); b.hi[1] = std::max(b.hi[1], y);
            b.low = std::min(b.low, h); b.high = std::max(b.high, h);
        }
        return;
    }
    // the plane: across the area-weighted normal of the triangles taking part (none, where
    // they stand steeper than 75 degrees to d: the box's heights are then as tight)
    double n[3] = {0.0, 0.0, 0.0};
    int taking = 0;
    for (int i = node.first; i < node.first + node.count; ++i) {
        if (!takes_part(i)) continue;
        ++taking;
        const double *f = &body->normals[3 * i];
        double along = dot3(f, d), sign = along >= 0.0 ? 1.0 : -1.0;
        n[0] += sign * body->areas[i] * dot3(f, u);
        n[1] += sign * body->areas[i] * dot3(f, w);
        n[2] += sign * body->areas[i] * along;
    }
    if (taking == 0) return;
    double length = std::sqrt(dot3(n, n));
    if (length > 0.0 && std::fabs(n[2]) >= 0.25 * length) {
        b.g[0] = -n[0] / n[2];
        b.g[1] = -n[1] / n[2];
    }
    auto extend = [&](int32_t v) {
        const double *p = vertex(v);
        b.lo[0] = std::min(b.lo[0], p[0]); b.hi[0] = std::max(b.hi[0], p[0]);
        b.lo[1] = std::min(b.lo[1], p[1]); b.hi[1] = std::max(b.hi[1], p[1]);
        double r = p[2] - b.g[0] * p[0] - b.g[1] * p[1];
        b.low = std::min(b.low, r); b.high = std::max(b.high, r);
    };
    // every triangle takes part: the node's distinct vertices (the same extremes, each
    // vertex met once); else the vertices of those that do
    if (taking == node.count) {
        const int32_t *v = body->node_vertices.data();
        for (int32_t k = body->node_vertex_start[index]; k < body->node_vertex_start[index + 1]; ++k)
            extend(v[k]);
        return;
    }
    for (int i = node.first; i < node.first + node.count; ++i) {
        if (!takes_part(i)) continue;
        for (int c = 0; c < 3; ++c) extend(body->faces[3 * i + c]);
    }
}

// A contact feature: the gap along d at which it closes, its unit normal (oriented n . d >= 0:
// the gap changes by -n . dp / n . d when the moving body's point moves by dp), the point on
// the moving body (fixed frame) and what meets what (0 a moving vertex on a fixed face,
// 1 a fixed vertex on a moving face, 2 an edge across an edge) with the two triangles.
// `room`: how far the moving body may slide across d before the feature stops being one
// (the vertex leaves the other triangle's shadow, the crossing runs off an edge).
using kneeseat::Feature;

// distance from q to the nearest edge line of triangle (p0, p1, p2) in the plane
inline double edge_distance(const double *p0, const double *p1, const double *p2, double qx, double qy) {
    const double *v[3] = {p0, p1, p2};
    double least = kInf;
    for (int i = 0; i < 3; ++i) {
        const double *a = v[i], *b = v[(i + 1) % 3];
        double ex = b[0] - a[0], ey = b[1] - a[1], length = std::sqrt(ex * ex + ey * ey);
        if (length == 0.0) continue;
        least = std::min(least, std::fabs(cross2(ex, ey, qx - a[0], qy - a[1])) / length);
    }
    return least;
}

// What a pair's least gap computed from the triangles' planes may fall short of the one
// computed from their features by rounding (m): far above it, far below any resolution.
constexpr double kPlaneSlack = 1e-9;

struct Visit {          // a pair of nodes to open: fixed, moving, and their gap's lower bound
    int32_t a, b;
    double lo;
};

struct Sweep {
    View *fixed, *moving;
    double R[9], T[3];                 // fixed_from_moving
    double cos_, sin_, du, dw, dh;     // moving view -> fixed view: q = Rot q' + (du, dw)
    double behind, window, limit;
    double short_of = -kInf;           // stop once the travel is known to be below this
    uint32_t stamp = 0;                // the moving vertices' (a view's own count)
    uint64_t query = 0;                // the moving node bounds' (`Body::queries`)
    bool want_features = false;
    // results
    double best;
    bool buried;
    // the pair (moving face, fixed face: the caller's ids) that set `best` last, or buried
    // the pose: the one that stops a search short (-1: none yet)
    int64_t stopper[2] = {-1, -1};
    std::vector<Feature> features;
    std::vector<Visit> visits;         // the traversal's stack, kept between queries
    long pairs = 0;

    void place(const double *pose);
    const double *moving_vertex(int32_t i);
    const Placed &moving_bound(int b);
    bool node_bounds(int a, int b, double &lo, double &hi);
    double planes_least(const double *const A[3], const double *const B[3], int32_t ta,
                        int32_t tb, const double lo[2], const double hi[2]);
    // the features beyond `keep` past the best contact are kept only among the `cap` with
    // the least gaps (0: all): on conforming surfaces a wide window holds hundreds that name
    // the same few pairs a move closes first. `nearest` holds the least gaps recorded so
    // far (a max-heap of at most `cap`); once it is full, the search's limit falls to the
    // largest of them, or to `keep` past the best contact then, whichever is further (the
    // best only falls, and the cap-th least gap of all is no larger, so nothing kept in the
    // end lies beyond it, `kept_features`; a search that sets its limit anew starts
    // afresh, `run`)
    size_t cap = 0;
    double keep = 0.0;
    std::vector<double> nearest;
    double cutoff() const { return std::min(best + window, limit); }
    void triangle_pair(int32_t moving_face, int32_t fixed_face);
    void run(const int64_t *seeds = nullptr, Py_ssize_t count = 0);
};

void Sweep::place(const double *pose) {
    for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 3; ++c) R[3 * r + c] = pose[4 * r + c];
        T[r] = pose[4 * r + 3];
    }
    // the moving view's u turned into the fixed frame, seen in the fixed view's (u, w)
    double ru[3];
    for (int k = 0; k < 3; ++k)
        ru[k] = R[3 * k] * moving->u[0] + R[3 * k + 1] * moving->u[1] + R[3 * k + 2] * moving->u[2];
    cos_ = dot3(ru, fixed->u);
    sin_ = dot3(ru, fixed->w);
    double norm = std::sqrt(cos_ * cos_ + sin_ * sin_);
    cos_ /= norm;
    sin_ /= norm;
    du = dot3(T, fixed->u);
    dw = dot3(T, fixed->w);
    dh = dot3(T, fixed->d);
    if (++moving->placed_stamp[0] == 0) {        // slot 0 holds the running stamp
        std::fill(moving->placed_stamp.begin(), moving->placed_stamp.end(), 0);
        moving->placed_stamp[0] = 1;
    }
    stamp = moving->placed_stamp[0];
    query = ++moving->body->queries;
}

KNEESEAT_INLINE const double *Sweep::moving_vertex(int32_t i) {
    uint32_t &mark = moving->placed_stamp[i + 1];
    double *out = &moving->placed[3 * i];
    if (mark != stamp) {
        const double *p = moving->vertex(i);
        out[0] = cos_ * p[0] - sin_ * p[1] + du;
        out[1] = sin_ * p[0] + cos_ * p[1] + dw;
        out[2] = p[2] + dh;
        mark = stamp;
    }
    return out;
}

// Moving node b's bound placed for the current query (its rectangle and plane turned and
// shifted into the fixed view), computed once a query: a node meets many fixed nodes.
KNEESEAT_INLINE const Placed &Sweep::moving_bound(int b) {
    Placed &P = moving->placed_bounds[b];
    if (P.stamp == query) return P;
    P.stamp = query;
    const Bound &B = moving->bound(b);
    P.low = B.low;
    P.high = B.high;
    P.width = (B.hi[0] - B.lo[0]) + (B.hi[1] - B.lo[1]);
    if (B.low > B.high) return P;
    double cx = 0.5 * (B.lo[0] + B.hi[0]), cy = 0.5 * (B.lo[1] + B.hi[1]);
    double ex = 0.5 * (B.hi[0] - B.lo[0]), ey = 0.5 * (B.hi[1] - B.lo[1]);
    P.x = cos_ * cx - sin_ * cy + du;
    P.y = sin_ * cx + cos_ * cy + dw;
    P.rx = std::fabs(cos_) * ex + std::fabs(sin_) * ey;
    P.ry = std::fabs(sin_) * ex + std::fabs(cos_) * ey;
    P.g[0] = cos_ * B.g[0] - sin_ * B.g[1];
    P.g[1] = sin_ * B.g[0] + cos_ * B.g[1];
    P.c = dh - P.g[0] * du - P.g[1] * dw;
    return P;
}

// Bounds of the gap along d between fixed node a and moving node b over their shadows'
// overlap; false when the shadows do not overlap or a node has no triangle taking part.
KNEESEAT_INLINE bool Sweep::node_bounds(int a, int b, double &lo, double &hi) {
    const Bound &A = fixed->bound(a);
    const Placed &B = moving_bound(b);
    if (A.low > A.high || B.low > B.high) return false;
    double x0 = std::max(A.lo[0], B.x - B.rx), x1 = std::min(A.hi[0], B.x + B.rx);
    double y0 = std::max(A.lo[1], B.y - B.ry), y1 = std::min(A.hi[1], B.y + B.ry);
    if (x0 > x1 || y0 > y1) return false;
    // the difference of the planes over the overlap is least at the corner its slopes
    // point away from and largest at the one they point to (rounding is monotonic: no
    // other corner computes lower or higher)
    double s0 = A.g[0] - B.g[0], s1 = A.g[1] - B.g[1];
    lo = (s0 * (s0 >= 0.0 ? x0 : x1) + s1 * (s1 >= 0.0 ? y0 : y1) - B.c) + A.low - B.high;
    hi = (s0 * (s0 >= 0.0 ? x1 : x0) + s1 * (s1 >= 0.0 ? y1 : y0) - B.c) + A.high - B.low;
    return true;
}

// Twice the signed area of triangle (p0, p1, p2) of the plane.
inline double shadow_area(const double *p0, const double *p1, const double *p2) {
    return cross2(p1[0] - p0[0], p1[1] - p0[1], p2[0] - p0[0], p2[1] - p0[1]);
}

// q inside triangle (p0, p1, p2) of the plane (edges included; `area` its shadow_area): the
// height there
inline bool height_at(const double *p0, const double *p1, const double *p2, double area, double qx,
                      double qy, double &h) {
    if (area == 0.0) return false;
    double l1 = cross2(qx - p0[0], qy - p0[1], p2[0] - p0[0], p2[1] - p0[1]) / area;
    if (l1 < 0.0) return false;
    double l2 = cross2(p1[0] - p0[0], p1[1] - p0[1], qx - p0[0], qy - p0[1]) / area;
    if (l2 < 0.0) return false;
    double l0 = 1.0 - l1 - l2;
    if (l0 < 0.0) return false;
    h = l0 * p0[2] + l1 * p1[2] + l2 * p2[2];
    return true;
}

// The fifteen features of one pair of triangles seen along d (A moving, B fixed, each
// vertex (u, w, h)): the least and the largest gap along d over the overlap of their shadows
// and which feature gives the least (kind -1: the shadows do not overlap).
struct PairGap {
    double least = kInf, most = -kInf, at = 0.0, room = 0.0;
    int kind = -1, i_at = 0, j_at = 0;

    PairGap(const double *const A[3], const double *const B[3]);
};

PairGap::PairGap(const double *const A[3], const double *const B[3]) {
    double h;
    const double area_a = shadow_area(A[0], A[1], A[2]), area_b = shadow_area(B[0], B[1], B[2]);
    for (int i = 0; i < 3; ++i)
        if (height_at(B[0], B[1], B[2], area_b, A[i][0], A[i][1], h)) {
            double gap = h - A[i][2];
            if (gap < least) { least = gap; kind = 0; i_at = i; }
            most = std::max(most, gap);
        }
    for (int j = 0; j < 3; ++j)
        if (height_at(A[0], A[1], A[2], area_a, B[j][0], B[j][1], h)) {
            double gap = B[j][2] - h;
            if (gap < least) { least = gap; kind = 1; j_at = j; }
            most = std::max(most, gap);
        }
    for (int i = 0; i < 3; ++i) {
        const double *a0 = A[i], *a1 = A[(i + 1) % 3];
        double ax = a1[0] - a0[0], ay = a1[1] - a0[1];
        for (int j = 0; j < 3; ++j) {
            const double *b0 = B[j], *b1 = B[(j + 1) % 3];
            double bx = b1[0] - b0[0], by = b1[1] - b0[1];
            double den = cross2(ax, ay, bx, by);
            if (den == 0.0) continue;
            double cx = b0[0] - a0[0], cy = b0[1] - a0[1];
            double s = cross2(cx, cy, bx, by) / den;
            if (s < 0.0 || s > 1.0) continue;
            double r = cross2(cx, cy, ax, ay) / den;
            if (r < 0.0 || r > 1.0) continue;
            double gap = (b0[2] + r * (b1[2] - b0[2])) - (a0[2] + s * (a1[2] - a0[2]));
            if (gap < least) {
                least = gap; kind = 2; i_at = i; j_at = j; at = s;
                double la = std::sqrt(ax * ax + ay * ay), lb = std::sqrt(bx * bx + by * by);
                room = std::fabs(den) * std::min(std::min(s, 1.0 - s) / lb, std::min(r, 1.0 - r) / la);
            }
            most = std::max(most, gap);
        }
    }
}

// A lower bound of the gap along d between moving triangle ta and fixed triangle tb (their
// vertices A and B placed, the overlap of their shadows' boxes [lo, hi]): the gap between
// their planes is affine over the shadows, so over that overlap (which holds the overlap
// of the shadows) it is least at the corner its slopes point away from. Short of the least
// gap their features give by rounding only (`kPlaneSlack`); -inf where a slope is not to
// be trusted.
KNEESEAT_INLINE double Sweep::planes_least(const double *const A[3], const double *const B[3],
                                           int32_t ta, int32_t tb, const double lo[2],
                                           const double hi[2]) {
    const double *ga = moving->slope(ta), *gb = fixed->slope(tb);
    if (!ga || !gb) return -kInf;
    // the moving triangle's slope turned into the fixed view
    double ax = cos_ * ga[0] - sin_ * ga[1], ay = sin_ * ga[0] + cos_ * ga[1];
    double sx = gb[0] - ax, sy = gb[1] - ay;
    double qx = sx >= 0.0 ? lo[0] : hi[0], qy = sy >= 0.0 ? lo[1] : hi[1];
    return (B[0][2] + gb[0] * (qx - B[0][0]) + gb[1] * (qy - B[0][1]))
           - (A[0][2] + ax * (qx - A[0][0]) + ay * (qy - A[0][1]));
}

// The overlap [lo, hi] of the boxes of the shadows of A and B (each vertex (u, w, h));
// false where they are apart.
KNEESEAT_INLINE bool boxes_overlap(const double *const A[3], const double *const B[3],
                                   double lo[2], double hi[2]) {
    for (int k = 0; k < 2; ++k) {
        double alo = std::min(std::min(A[0][k], A[1][k]), A[2][k]);
        double ahi = std::max(std::max(A[0][k], A[1][k]), A[2][k]);
        double blo = std::min(std::min(B[0][k], B[1][k]), B[2][k]);
        double bhi = std::max(std::max(B[0][k], B[1][k]), B[2][k]);
        if (ahi < blo || bhi < alo) return false;
        lo[k] = std::max(alo, blo);
        hi[k] = std::min(ahi, bhi);
    }
    return true;
}

void Sweep::triangle_pair(int32_t ta, int32_t tb) {
    ++pairs;
    const Body &mb = *moving->body, &fb = *fixed->body;
    const int32_t *fa = &mb.faces[3 * ta], *ff = &fb.faces[3 * tb];
    const double *A[3] = {moving_vertex(fa[0]), moving_vertex(fa[1]), moving_vertex(fa[2])};
    const double *B[3] = {fixed->vertex(ff[0]), fixed->vertex(ff[1]), fixed->vertex(ff[2])};
    // cheap rejections first: shadows' boxes apart, or every point of B further along d
    // than every point of A by more than the cutoff
    double lo[2], hi[2];
    if (!boxes_overlap(A, B, lo, hi)) return;
    double alow = std::min(std::min(A[0][2], A[1][2]), A[2][2]);
    double ahigh = std::max(std::max(A[0][2], A[1][2]), A[2][2]);
    double blow = std::min(std::min(B[0][2], B[1][2]), B[2][2]);
    double bhigh = std::max(std::max(B[0][2], B[1][2]), B[2][2]);
    if (blow - ahigh > cutoff() || bhigh - alow < -behind) return;
    if (planes_least(A, B, ta, tb, lo, hi) > cutoff() + kPlaneSlack) return;
    const PairGap g(A, B);
    if (g.kind < 0 || g.most < -behind) return;      // shadows apart, or wholly behind
    if (g.least <= -behind) {
        buried = true;
        stopper[0] = mb.face_id[ta];
        stopper[1] = fb.face_id[tb];
        return;
    }
    if (g.least > cutoff()) return;
    if (g.least < best) {
        best = g.least;
        stopper[0] = mb.face_id[ta];
        stopper[1] = fb.face_id[tb];
    }
    if (!want_features) return;
    const int kind = g.kind, i_at = g.i_at, j_at = g.j_at;
    Feature f;
    f.gap = g.least;
    f.kind = kind;
    f.moving_face = mb.face_id[ta];
    f.fixed_face = fb.face_id[tb];
    double world[3][3];                        // the moving triangle in the fixed frame
    for (int c = 0; c < 3; ++c) {
        const double *p = &mb.vertices[3 * fa[c]];
        for (int k = 0; k < 3; ++k) world[c][k] = R[3 * k] * p[0] + R[3 * k + 1] * p[1] + R[3 * k + 2] * p[2] + T[k];
    }
    const double *d = fixed->d;
    double n[3];
    if (kind == 0) {
        for (int k = 0; k < 3; ++k) { n[k] = fb.normals[3 * tb + k]; f.point[k] = world[i_at][k]; }
        f.room = edge_distance(B[0], B[1], B[2], A[i_at][0], A[i_at][1]);
    } else if (kind == 1) {
        f.room = edge_distance(A[0], A[1], A[2], B[j_at][0], B[j_at][1]);
        const double *q = &fb.vertices[3 * ff[j_at]], *m = &mb.normals[3 * ta];
        for (int k = 0; k < 3; ++k) {
            n[k] = R[3 * k] * m[0] + R[3 * k + 1] * m[1] + R[3 * k + 2] * m[2];
            f.point[k] = q[k] - g.least * d[k];
        }
    } else {
        f.room = g.room;
        const double *a0 = world[i_at], *a1 = world[(i_at + 1) % 3];
        const double *b0 = &fb.vertices[3 * ff[j_at]], *b1 = &fb.vertices[3 * ff[(j_at + 1) % 3]];
        double ea[3], eb[3];
        for (int k = 0; k < 3; ++k) { ea[k] = a1[k] - a0[k]; eb[k] = b1[k] - b0[k]; f.point[k] = a0[k] + g.at * ea[k]; }
        n[0] = ea[1] * eb[2] - ea[2] * eb[1];
        n[1] = ea[2] * eb[0] - ea[0] * eb[2];
        n[2] = ea[0] * eb[1] - ea[1] * eb[0];
        double length = std::sqrt(dot3(n, n));
        for (int k = 0; k < 3; ++k) n[k] = length > 0.0 ? n[k] / length : 0.0;
    }
    double sign = dot3(n, d) >= 0.0 ? 1.0 : -1.0;
    for (int k = 0; k < 3; ++k) f.normal[k] = sign * n[k];
    features.push_back(f);
    if (cap != 0) {
        nearest.push_back(f.gap);
        std::push_heap(nearest.begin(), nearest.end());
        if (nearest.size() > cap) {
            std::pop_heap(nearest.begin(), nearest.end());
            nearest.pop_back();
        }
        if (nearest.size() == cap) limit = std::min(limit, std::max(nearest.front(), best + keep));
    }
}

// `seeds`: pairs of triangles (moving face, fixed face, as given) likely to close first
// from the pose. Their gaps bound the travel from above before the traversal starts, so it
// prunes from its first visit; they are met again in the traversal, which alone records
// features, so what a query returns is the same with or without them.
void Sweep::run(const int64_t *seeds, Py_ssize_t count) {
    best = kInf;
    buried = false;
    stopper[0] = stopper[1] = -1;
    features.clear();
    nearest.clear();
    const Body &fb = *fixed->body, &mb = *moving->body;
    if (fb.nodes.empty() || mb.nodes.empty()) return;
    const bool record = want_features;
    want_features = false;
    for (Py_ssize_t k = 0; k < count; ++k) {
        int32_t j = mb.tree_index[seeds[2 * k]], i = fb.tree_index[seeds[2 * k + 1]];
        if (fixed->takes_part(i) && moving->takes_part(j)) triangle_pair(j, i);
        if (buried || best < short_of) break;
    }
    want_features = record;
    if (buried || best < short_of) return;
    // depth first, the child pair with the lower bound first: the first leaves reached set
    // a tight cutoff early, and a stack costs far less than a heap per visit
    std::vector<Visit> &stack = visits;
    stack.clear();
    double lo, hi;
    if (!node_bounds(0, 0, lo, hi) || hi < -behind) return;
    stack.push_back({0, 0, lo});
    while (!stack.empty()) {
        Visit v = stack.back();
        stack.pop_back();
        // down the tree from v: the child with the lower bound next (the other waits on the
        // stack), as a stack alone would take them
        while (v.lo <= cutoff()) {
            const Node &na = fb.nodes[v.a], &nb = mb.nodes[v.b];
            if (na.right < 0 && nb.right < 0) {
                for (int i = na.first; i < na.first + na.count; ++i) {
                    if (!fixed->takes_part(i)) continue;
                    for (int j = nb.first; j < nb.first + nb.count; ++j) {
                        if (!moving->takes_part(j)) continue;
                        triangle_pair(j, i);
                        if (buried || best < short_of) return;
                    }
                }
                break;
            }
            // open the node whose shadow is wider (a leaf is never opened; the pair's bounds
            // are placed already)
            const Bound &A = fixed->bound(v.a);
            double wa = (A.hi[0] - A.lo[0]) + (A.hi[1] - A.lo[1]);
            double wb = moving_bound(v.b).width;
            bool open_fixed = nb.right < 0 || (na.right >= 0 && wa >= wb);
            int kids[2] = {open_fixed ? v.a + 1 : v.b + 1, open_fixed ? na.right : nb.right};
            Visit next[2];
            int n = 0;
            for (int kid : kids) {
                int a = open_fixed ? kid : v.a, b = open_fixed ? v.b : kid;
                if (node_bounds(a, b, lo, hi) && hi >= -behind && lo <= cutoff())
                    next[n++] = {a, b, lo};
            }
            if (n == 0) break;
            if (n == 2) {
                if (next[0].lo < next[1].lo) std::swap(next[0], next[1]);
                stack.push_back(next[0]);
            }
            v = next[n - 1];
        }
    }
}

// ---- Python -----------------------------------------------------------------------------

struct PyBody {
    PyObject_HEAD
    Body *body;
};

struct PyView {
    PyObject_HEAD
    View *view;
    PyObject *body;     // keeps the Body alive
};

PyTypeObject BodyType = {PyVarObject_HEAD_INIT(nullptr, 0)};
PyTypeObject ViewType = {PyVarObject_HEAD_INIT(nullptr, 0)};

using kneeseat::get_buffer;

void body_dealloc(PyBody *self) {
    delete self->body;
    Py_TYPE(self)->tp_free(reinterpret_cast<PyObject *>(self));
}

int body_init(PyBody *self, PyObject *args, PyObject *) {
    PyObject *vo, *fo, *so;
    if (!PyArg_ParseTuple(args, "OOO", &vo, &fo, &so)) return -1;
    Py_buffer vb, fb, sb;
    if (!get_buffer(vo, &vb, "d", 8, "vertices")) return -1;
    if (!get_buffer(fo, &fb, "q", 8, "faces")) { PyBuffer_Release(&vb); return -1; }
    if (!get_buffer(so, &sb, "b", 1, "facing")) { PyBuffer_Release(&vb); PyBuffer_Release(&fb); return -1; }
    Py_ssize_t nv = vb.len / 24, nf = fb.len / 24;
    int ok = vb.len % 24 == 0 && fb.len % 24 == 0 && sb.len == nf;
    const int64_t *faces = static_cast<const int64_t *>(fb.buf);
    for (Py_ssize_t i = 0; ok && i < 3 * nf; ++i) ok = faces[i] >= 0 && faces[i] < nv;
    if (!ok) {
        PyErr_SetString(PyExc_ValueError, "Body: vertices (n, 3), faces (m, 3) indexing them, facing (m,)");
    } else {
        // the hierarchy is built on the buffers alone: other threads may run meanwhile (a
        // scene's bodies are built side by side, kneeseat_core/sweep/scene.py)
        Body *body = new Body();
        Py_BEGIN_ALLOW_THREADS
        make_body(*body, static_cast<const double *>(vb.buf), nv, faces, nf,
                  static_cast<const int8_t *>(sb.buf));
        Py_END_ALLOW_THREADS
        delete self->body;
        self->body = body;
    }
    PyBuffer_Release(&vb); PyBuffer_Release(&fb); PyBuffer_Release(&sb);
    return ok ? 0 : -1;
}

void view_dealloc(PyView *self) {
    delete self->view;
    Py_XDECREF(self->body);
    Py_TYPE(self)->tp_free(reinterpret_cast<PyObject *>(self));
}

int view_init(PyView *self, PyObject *args, PyObject *) {
    PyObject *bo, *dobj;
    int side;
    if (!PyArg_ParseTuple(args, "O!Oi", &BodyType, &bo, &dobj, &side)) return -1;
    Py_buffer db;
    if (!get_buffer(dobj, &db, "d", 8, "direction")) return -1;
    const double *d = static_cast<const double *>(db.buf);
    bool ok = db.len == 24 && std::fabs(dot3(d, d) - 1.0) < 1e-9 && (side == 1 || side == -1) &&
              reinterpret_cast<PyBody *>(bo)->body != nullptr;
    if (ok) {
        delete self->view;
        self->view = new View(*reinterpret_cast<PyBody *>(bo)->body, d, side);
        Py_INCREF(bo);
        Py_XDECREF(self->body);
        self->body = bo;
    } else {
        PyErr_SetString(PyExc_ValueError, "View: a unit direction (3,) and side +1 or -1");
    }
    PyBuffer_Release(&db);
    return ok ? 0 : -1;
}

PyObject *view_filled(PyView *self, PyObject *) {
    if (!self->view) Py_RETURN_NONE;
    long n = 0;
    for (uint8_t b : self->view->has_bound) n += b;
    return PyLong_FromLong(n);
}

PyMethodDef view_methods[] = {
    {"filled", reinterpret_cast<PyCFunction>(view_filled), METH_NOARGS, "Nodes bounded so far."},
    {nullptr, nullptr, 0, nullptr}};

// A call's two views, checked: the fixed body's (side -1) and the moving body's (side +1).
bool take_views(PyObject *fo, PyObject *mo, Sweep &s) {
    s.fixed = reinterpret_cast<PyView *>(fo)->view;
    s.moving = reinterpret_cast<PyView *>(mo)->view;
    if (s.fixed && s.moving && s.fixed->side == -1 && s.moving->side == 1) return true;
    PyErr_SetString(PyExc_ValueError, "a fixed view (side -1) and a moving view (side +1)");
    return false;
}

// Whether each of `count` pairs (moving face, fixed face, as given) names faces the sweep's
// bodies have.
bool faces_of(const Sweep &s, const int64_t *pairs, Py_ssize_t count) {
    const Py_ssize_t nm = static_cast<Py_ssize_t>(s.moving->body->tree_index.size());
    const Py_ssize_t nf = static_cast<Py_ssize_t>(s.fixed->body->tree_index.size());
    for (Py_ssize_t j = 0; j < count; ++j)
        if (pairs[2 * j] < 0 || pairs[2 * j] >= nm || pairs[2 * j + 1] < 0 || pairs[2 * j + 1] >= nf)
            return false;
    return true;
}

bool parse_sweep(PyObject *args, Sweep &s, Py_buffer &poses, Py_ssize_t &count, double &window,
                 PyObject **seeds = nullptr) {
    PyObject *fo, *mo, *po, *so = Py_None;
    if (!PyArg_ParseTuple(args, seeds ? "O!O!Oddd|dO" : "O!O!Oddd|d", &ViewType, &fo, &ViewType, &mo, &po,
                          &s.behind, &window, &s.limit, &s.short_of, &so))
        return false;
    if (seeds) *seeds = so;
    if (!take_views(fo, mo, s)) return false;
    if (!get_buffer(po, &poses, "d", 8, "poses")) return false;
    if (poses.len % 128 != 0 || !(s.behind >= 0.0) || !(window >= 0.0) || !(s.limit >= 0.0) ||
        std::isnan(s.short_of)) {
        PyErr_SetString(PyExc_ValueError, "poses (k, 4, 4); behind, window and limit not negative, short_of a number");
        PyBuffer_Release(&poses);
        return false;
    }
    count = poses.len / 128;
    return true;
}

// travels(fixed_view, moving_view, poses, behind, window, limit[, short_of])
//   -> (travels, buried, pairs); a travel below short_of is where the search stopped: the
//   travel is at most that
PyObject *travels(PyObject *, PyObject *args) {
    Sweep s;
    Py_buffer poses;
    Py_ssize_t count;
    double window;
    if (!parse_sweep(args, s, poses, count, window)) return nullptr;
    s.window = 0.0;
    std::vector<double> out(count);
    std::vector<int8_t> buried(count);
    const double *p = static_cast<const double *>(poses.buf);
    for (Py_ssize_t i = 0; i < count; ++i) {
        s.place(p + 16 * i);
        s.run();
        out[i] = s.buried ? -kInf : s.best;
        buried[i] = s.buried;
    }
    PyBuffer_Release(&poses);
    return Py_BuildValue("(y#y#l)", reinterpret_cast<const char *>(out.data()), count * 8,
                         reinterpret_cast<const char *>(buried.data()), count, s.pairs);
}

// The features a search keeps: those within its window past the best contact, and of the
// ones beyond `keep` past it only the `cap` with the least gaps, ties kept (Sweep::cap).
// What it keeps does not hang on the order it met them in.
std::vector<Feature> kept_features(const Sweep &s) {
    std::vector<Feature> kept;
    for (const Feature &f : s.features)
        if (f.gap <= s.best + s.window) kept.push_back(f);
    if (s.cap != 0 && kept.size() > s.cap) {
        std::vector<double> gaps;
        gaps.reserve(kept.size());
        for (const Feature &f : kept) gaps.push_back(f.gap);
        std::nth_element(gaps.begin(), gaps.begin() + (s.cap - 1), gaps.end());
        const double bound = std::max(gaps[s.cap - 1], s.best + s.keep);
        kept.erase(std::remove_if(kept.begin(), kept.end(),
                                  [bound](const Feature &f) { return f.gap > bound; }),
                   kept.end());
    }
    return kept;
}

// contacts(fixed_view, moving_view, pose, behind, window, limit[, short_of[, seeds]])
//   -> (travel, buried, features (bytes of Feature), pairs); a travel below short_of is
//   where the search stopped (the travel is at most that, the features are partial);
//   seeds (k, 2) of (moving face, fixed face): pairs asked first (Sweep::run)
PyObject *contacts(PyObject *, PyObject *args) {
    Sweep s;
    Py_buffer poses, seeds;
    Py_ssize_t count, k = 0;
    double window;
    PyObject *so;
    if (!parse_sweep(args, s, poses, count, window, &so)) return nullptr;
    if (count != 1) {
        PyBuffer_Release(&poses);
        PyErr_SetString(PyExc_ValueError, "contacts: one pose (4, 4)");
        return nullptr;
    }
    const int64_t *pairs = nullptr;
    if (so != Py_None) {
        if (!get_buffer(so, &seeds, "q", 8, "seeds")) {
            PyBuffer_Release(&poses);
            return nullptr;
        }
        k = seeds.len / 16;
        pairs = static_cast<const int64_t *>(seeds.buf);
        if (seeds.len % 16 != 0 || !faces_of(s, pairs, k)) {
            PyBuffer_Release(&poses);
            PyBuffer_Release(&seeds);
            PyErr_SetString(PyExc_ValueError, "contacts: seeds (k, 2) of face indices (moving, fixed)");
            return nullptr;
        }
    }
    s.window = window;
    s.want_features = true;
    s.place(static_cast<const double *>(poses.buf));
    s.run(pairs, k);
    PyBuffer_Release(&poses);
    if (pairs) PyBuffer_Release(&seeds);
    std::vector<Feature> kept;
    if (!s.buried) kept = kept_features(s);
    static const char nothing = 0;
    return Py_BuildValue("(dNy#l)", s.buried ? -kInf : s.best, PyBool_FromLong(s.buried),
                         kept.empty() ? &nothing : reinterpret_cast<const char *>(kept.data()),
                         static_cast<Py_ssize_t>(kept.size() * sizeof(Feature)), s.pairs);
}

// The least of `best` and the gaps along d from the moving body's vertex `i` (placed by
// the sweep) up to a front face of the fixed body, over faces no more than `behind` below
// it (a branch that cannot go below `best` is not opened).
double vertex_gap(Sweep &s, int32_t i, double behind, double best, std::vector<int32_t> &stack) {
    const double *q = s.moving_vertex(i);
    const Body &fb = *s.fixed->body;
    stack.clear();
    stack.push_back(0);
    while (!stack.empty()) {
        int index = stack.back();
        stack.pop_back();
        const Bound &b = s.fixed->bound(index);
        if (b.low > b.high || q[0] < b.lo[0] || q[0] > b.hi[0] || q[1] < b.lo[1] || q[1] > b.hi[1])
            continue;
        double plane = b.g[0] * q[0] + b.g[1] * q[1] - q[2];
        if (plane + b.high < -behind || plane + b.low >= best) continue;
        const Node &node = fb.nodes[index];
        if (node.right >= 0) {
            stack.push_back(index + 1);
            stack.push_back(node.right);
            continue;
        }
        for (int t = node.first; t < node.first + node.count; ++t) {
            if (!s.fixed->takes_part(t)) continue;
            const int32_t *f = &fb.faces[3 * t];
            double h;
            const double *p0 = s.fixed->vertex(f[0]), *p1 = s.fixed->vertex(f[1]), *p2 = s.fixed->vertex(f[2]);
            if (height_at(p0, p1, p2, shadow_area(p0, p1, p2), q[0], q[1], h)) {
                double gap = h - q[2];
                if (gap >= -behind && gap < best) best = gap;
            }
        }
    }
    return best;
}

// A buffer `what` of `count` 8-byte items of `format` ("d" or "q"), held on success;
// false with the error set otherwise.
bool get_sized(PyObject *obj, Py_buffer &view, const char *format, Py_ssize_t count, const char *what) {
    if (!get_buffer(obj, &view, format, 8, what)) return false;
    if (view.len == 8 * count) return true;
    PyErr_Format(PyExc_ValueError, "%s has the wrong shape", what);
    PyBuffer_Release(&view);
    return false;
}

// How many of a move's witnesses are ranked in the first pass (witness_short).
constexpr int kFirstWitnesses = 8;

// Whether the pair of triangles (moving face, fixed face, as given) closes short of
// `needed` with the moving body placed by the sweep (the least gap over the overlap of
// their shadows; a pair lying wholly more than `behind` below not counting); the moving
// triangle's vertices are added to `vertices` otherwise.
bool pair_short(Sweep &s, const int64_t *pair, double needed, double behind, std::vector<int32_t> &vertices) {
    const Body &mb = *s.moving->body, &fb = *s.fixed->body;
    const int32_t ta = mb.tree_index[pair[0]], tb = fb.tree_index[pair[1]];
    const int32_t *fa = &mb.faces[3 * ta], *ff = &fb.faces[3 * tb];
    const double *A[3] = {s.moving_vertex(fa[0]), s.moving_vertex(fa[1]), s.moving_vertex(fa[2])};
    const double *B[3] = {s.fixed->vertex(ff[0]), s.fixed->vertex(ff[1]), s.fixed->vertex(ff[2])};
    double lo[2], hi[2];
    // shadows apart, or the planes' bound at or beyond `needed` by more than rounding: no
    // feature closes short of it
    if (boxes_overlap(A, B, lo, hi) && s.planes_least(A, B, ta, tb, lo, hi) < needed + kPlaneSlack) {
        PairGap g(A, B);
        if (g.kind >= 0 && g.most >= -behind && g.least < needed) return true;
    }
    vertices.insert(vertices.end(), fa, fa + 3);
    return false;
}

// Whether one of the moving body's `vertices` (placed by the sweep; repeats allowed) closes
// short of `needed` onto whatever front face of the fixed body lies under it (a face more
// than `deepest` above the vertex not counting).
bool vertex_short(Sweep &s, std::vector<int32_t> &vertices, double needed, double deepest,
                  std::vector<int32_t> &stack) {
    if (s.fixed->body->nodes.empty()) return false;
    // each vertex once (the triangles of a contact share most of theirs)
    std::sort(vertices.begin(), vertices.end());
    vertices.erase(std::unique(vertices.begin(), vertices.end()), vertices.end());
    double least = kInf;
    for (int32_t v : vertices) {
        least = vertex_gap(s, v, deepest, least, stack);
        if (least < needed) return true;
    }
    return false;
}

// The pairs that stopped a settle's earlier searches short (its stoppers: the caller's
// buffer of `stopping` pairs of face ids, newest first): the moves about one place run into
// the same part of the fixed body, of which the pool, taken near the place, may name nothing.
// Whether one of them closes short of `needed` with the moving body placed by the sweep.
bool stoppers_short(Sweep &s, const int64_t *stoppers, Py_ssize_t stopping, double needed, double behind,
                    std::vector<int32_t> &scratch) {
    for (Py_ssize_t j = 0; j < stopping; ++j) {
        scratch.clear();
        if (pair_short(s, stoppers + 2 * j, needed, behind, scratch)) return true;
    }
    return false;
}

// `pair` put first among the `stopping` stoppers (a buffer of room for `most`): moved there
// where it is one already, else added, the oldest going when the buffer is full.
void remember_stopper(int64_t *stoppers, Py_ssize_t &stopping, Py_ssize_t most, const int64_t pair[2]) {
    Py_ssize_t j = 0;
    while (j < stopping && !(stoppers[2 * j] == pair[0] && stoppers[2 * j + 1] == pair[1])) ++j;
    if (j == stopping && stopping < most) ++stopping;
    for (j = std::min(j, stopping - 1); j > 0; --j) {
        stoppers[2 * j] = stoppers[2 * j - 2];
        stoppers[2 * j + 1] = stoppers[2 * j - 1];
    }
    stoppers[0] = pair[0];
    stoppers[1] = pair[1];
}

// Whether a witness of the sweep's pose closes short of `needed`: the `count` features of a
// pool (gaps (k,), slopes (k, 3) over the lateral state, faces (k, 2)) that the pool's
// first-order model says close first after the lateral move `offset` (3,) from where it
// was taken, asked first closing first (pair_short: most moves are refuted by one of the
// first few), then the vertices of their moving triangles (vertex_short). Their pairs go
// to `picked` (all of them where none is short).
bool witness_short(Sweep &s, const double *gaps, const double *slopes, const int64_t *faces, Py_ssize_t k,
                   const double *offset, Py_ssize_t count, double needed, double behind, double deepest,
                   std::vector<std::pair<double, int32_t>> &ranked, std::vector<int64_t> &picked,
                   std::vector<int32_t> &vertices, std::vector<int32_t> &stack) {
    // one pass ranks every feature and keeps the first few in order (most moves are refuted
    // by one of them, at no cost of ordering the rest); the rest are ordered only when
    // those are not short
    ranked.resize(k);
    std::pair<double, int32_t> first[kFirstWitnesses];
    int kept = 0;
    for (Py_ssize_t j = 0; j < k; ++j) {
        const double *a = slopes + 3 * j;
        const std::pair<double, int32_t> f = {gaps[j] + a[0] * offset[0] + a[1] * offset[1] + a[2] * offset[2],
                                              static_cast<int32_t>(j)};
        ranked[j] = f;
        if (kept == kFirstWitnesses && !(f < first[kept - 1])) continue;
        int at = kept < kFirstWitnesses ? kept++ : kFirstWitnesses - 1;
        for (; at > 0 && f < first[at - 1]; --at) first[at] = first[at - 1];
        first[at] = f;
    }
    picked.clear();
    vertices.clear();
    const Py_ssize_t n = std::min(count, k), asked = std::min<Py_ssize_t>(n, kept);
    for (Py_ssize_t r = 0; r < asked; ++r) {
        const int64_t *pair = faces + 2 * first[r].second;
        picked.insert(picked.end(), pair, pair + 2);
        if (pair_short(s, pair, needed, behind, vertices)) return true;
    }
    if (n > asked) {
        if (n < k) std::nth_element(ranked.begin(), ranked.begin() + n, ranked.end());
        std::sort(ranked.begin(), ranked.begin() + n);
        for (Py_ssize_t r = asked; r < n; ++r) {
            const int64_t *pair = faces + 2 * ranked[r].second;
            picked.insert(picked.end(), pair, pair + 2);
            if (pair_short(s, pair, needed, behind, vertices)) return true;
        }
    }
    return vertex_short(s, vertices, needed, deepest, stack);
}

// first_unrefuted(fixed_view, moving_view, poses (m, 4, 4), needed (m,), gaps (k,), slopes
// (k, 3), faces (k, 2), offsets (m, 3), count, behind, deepest, start) -> (i, witnesses):
// the first pose i >= start whose needed travel is finite and none of whose witnesses
// closes short of it (m where there is none), and the pairs of triangles (c, 2) of its
// witnesses. A pose's witnesses are the `count` features of the pool (gaps, slopes, faces)
// that the pool says close first after its lateral offset from where the pool was taken,
// then the vertices of their moving triangles (see witness_short).
PyObject *first_unrefuted(PyObject *, PyObject *args) {
    PyObject *fo, *mo, *po, *no, *go, *so, *qo, *oo;
    Py_ssize_t count, start;
    double behind, deepest;
    Sweep s;
    if (!PyArg_ParseTuple(args, "O!O!OOOOOOnddn", &ViewType, &fo, &ViewType, &mo, &po, &no, &go, &so, &qo, &oo,
                          &count, &behind, &deepest, &start))
        return nullptr;
    if (!take_views(fo, mo, s)) return nullptr;
    Py_buffer bufs[6];
    int held = 0;
    bool ok = get_buffer(po, &bufs[0], "d", 8, "poses") && ++held;
    Py_ssize_t m = ok ? bufs[0].len / 128 : 0;
    if (ok && bufs[0].len != 128 * m) ok = false;
    ok = ok && get_sized(no, bufs[1], "d", m, "needed") && ++held;
    ok = ok && get_buffer(go, &bufs[2], "d", 8, "gaps") && ++held;
    Py_ssize_t k = ok ? bufs[2].len / 8 : 0;
    ok = ok && get_sized(so, bufs[3], "d", 3 * k, "slopes") && ++held;
    ok = ok && get_sized(qo, bufs[4], "q", 2 * k, "faces") && ++held;
    ok = ok && get_sized(oo, bufs[5], "d", 3 * m, "offsets") && ++held;
    const int64_t *faces = ok ? static_cast<const int64_t *>(bufs[4].buf) : nullptr;
    ok = ok && faces_of(s, faces, k);
    if (ok && (!(behind >= 0.0) || !(deepest >= 0.0) || count < 0 || start < 0)) ok = false;
    if (!ok) {
        if (!PyErr_Occurred())
            PyErr_SetString(PyExc_ValueError, "first_unrefuted: poses (m, 4, 4), needed (m,), gaps (k,), slopes "
                                              "(k, 3), faces (k, 2) of face indices, offsets (m, 3); count, "
                                              "behind, deepest and start not negative");
        for (int i = 0; i < held; ++i) PyBuffer_Release(&bufs[i]);
        return nullptr;
    }
    const double *p = static_cast<const double *>(bufs[0].buf), *needed = static_cast<const double *>(bufs[1].buf);
    const double *gaps = static_cast<const double *>(bufs[2].buf), *slopes = static_cast<const double *>(bufs[3].buf);
    const double *offsets = static_cast<const double *>(bufs[5].buf);
    std::vector<std::pair<double, int32_t>> ranked;
    std::vector<int64_t> picked;
    std::vector<int32_t> vertices, stack;
    Py_ssize_t i = start;
    for (; i < m; ++i) {
        if (!std::isfinite(needed[i])) continue;
        s.place(p + 16 * i);
        if (!witness_short(s, gaps, slopes, faces, k, offsets + 3 * i, count, needed[i], behind, deepest, ranked,
                           picked, vertices, stack))
            break;
    }
    for (int j = 0; j < held; ++j) PyBuffer_Release(&bufs[j]);
    if (i >= m) picked.clear();
    static const char nothing = 0;
    return Py_BuildValue("(ny#)", std::min(i, m), picked.empty() ? &nothing : reinterpret_cast<const char *>(picked.data()),
                         static_cast<Py_ssize_t>(picked.size() * 8));
}

// How far the moving body at `pose` can travel before no contact can happen any more: the
// distance between the bodies' bounding spheres' centres plus both radii (`bounds`: the
// moving body's centre in its frame, the fixed body's, the radii's sum).
double travel_limit(const double *pose, const double *bounds) {
    double d2 = 0.0;
    for (int r = 0; r < 3; ++r) {
        double c = pose[4 * r] * bounds[0] + pose[4 * r + 1] * bounds[1] + pose[4 * r + 2] * bounds[2] +
                   pose[4 * r + 3] - bounds[3 + r];
        d2 += c * c;
    }
    return std::sqrt(d2) + bounds[6];
}

enum Measured { kPlace = 0, kShort = 1, kLost = 2 };

// The pose moved along d to contact (kneeseat_core/settle/climb.py, `_Climb.arrive`): the
// travel searched from the pose lowered by enough that the lowered pose is free (`expected`
// the travel expected, negative where the pose may be in collision), lowered four times
// further while the lowered pose is buried; the features within `window` beyond kept in
// the sweep. kShort: the travel is below `short_of` (the search stops as soon as a gap
// says so); kLost: no contact along d, or buried beyond twice the limit.
Measured arrive(Sweep &s, const double *pose, double expected, double short_of, double window, double standoff,
                const double *bounds, const int64_t *seeds, Py_ssize_t k, long &queries) {
    double behind = std::max(0.0, -2.0 * expected) + standoff;
    const double limit = travel_limit(pose, bounds);
    s.window = window;
    s.short_of = short_of;
    s.place(pose);
    while (true) {
        s.behind = behind;
        s.limit = std::min(limit + behind, 1e300);
        s.want_features = true;
        s.run(seeds, k);
        ++queries;
        if (!s.buried) break;
        if (-behind < short_of) return kShort;     // the travel is below -behind
        behind *= 4.0;
        if (behind > 2.0 * limit) return kLost;
    }
    if (s.best < short_of) return kShort;
    return std::isfinite(s.best) ? kPlace : kLost;
}

// measure(fixed_view, moving_view, poses (m, 4, 4), needed (m,), expected (m,), near_window,
// wide_window, reach, gaps (k,), slopes (k, 3), faces (k, 2), moves (m, 3), shift (3,), count,
// standoff, deepest, bounds (7,), start, seeds (c, 2) | None, cap, keep, stoppers (s, 2)) ->
// (index, kind, travel, features, queries, pairs, wide): from pose `start` on, the first that
// none of its witnesses refutes (the `stoppers` first, then first_unrefuted's, at the lateral
// offset moves[i] + shift from where the pool was taken; with count 0 none is asked) moved
// along d to contact (arrive: expected[i], short of needed[i], the features within the wide
// window where that offset exceeds `reach` in a coordinate - `wide` - and within the near one
// elsewhere, of those beyond `keep` only the `cap` nearest: 0 keeps them all,
// `kept_features`); one found short is passed over, the pair that stopped its search put
// first in `stoppers` (written in place: pairs of face indices, newest first, -1 past the
// last; as many as it holds). kind kPlace: the pose `index` reached its travel, with the
// features (bytes of Feature); kLost: no contact along d from it; index m: every pose refuted
// or short. A search starts from the pose's witnesses and the stoppers, or from `seeds` where
// none are asked. A needed travel of +inf (or NaN) is passed over. Any pair that closes short
// of a pose's needed travel refutes it exactly, and seeds only bound a search, so the
// stoppers change how fast the answer comes, never the answer.
PyObject *measure(PyObject *, PyObject *args) {
    PyObject *fo, *mo, *po, *no, *eo, *go, *so, *qo, *oo, *ho, *bo, *co, *xo;
    Py_ssize_t count, start, cap;
    double near_window, wide_window, reach, standoff, deepest, keep;
    Sweep s;
    if (!PyArg_ParseTuple(args, "O!O!OOOdddOOOOOnddOnOndO", &ViewType, &fo, &ViewType, &mo, &po, &no, &eo,
                          &near_window, &wide_window, &reach, &go, &so, &qo, &oo, &ho, &count, &standoff,
                          &deepest, &bo, &start, &co, &cap, &keep, &xo))
        return nullptr;
    if (!take_views(fo, mo, s)) return nullptr;
    Py_buffer bufs[11];
    int held = 0;
    bool ok = get_buffer(po, &bufs[0], "d", 8, "poses") && ++held;
    Py_ssize_t m = ok ? bufs[0].len / 128 : 0;
    if (ok && bufs[0].len != 128 * m) ok = false;
    ok = ok && get_sized(no, bufs[1], "d", m, "needed") && ++held;
    ok = ok && get_sized(eo, bufs[2], "d", m, "expected") && ++held;
    ok = ok && get_buffer(go, &bufs[3], "d", 8, "gaps") && ++held;
    Py_ssize_t k = ok ? bufs[3].len / 8 : 0;
    ok = ok && get_sized(so, bufs[4], "d", 3 * k, "slopes") && ++held;
    ok = ok && get_sized(qo, bufs[5], "q", 2 * k, "faces") && ++held;
    ok = ok && get_sized(oo, bufs[6], "d", 3 * m, "moves") && ++held;
    ok = ok && get_sized(ho, bufs[7], "d", 3, "shift") && ++held;
    ok = ok && get_sized(bo, bufs[8], "d", 7, "bounds") && ++held;
    Py_ssize_t c = 0;
    const int64_t *seeds = nullptr;
    if (ok && co != Py_None) {
        ok = get_buffer(co, &bufs[9], "q", 8, "seeds") && ++held;
        c = ok ? bufs[9].len / 16 : 0;
        seeds = ok ? static_cast<const int64_t *>(bufs[9].buf) : nullptr;
        ok = ok && bufs[9].len == 16 * c && faces_of(s, seeds, c);
    }
    // the settle's stoppers (stoppers_short), the one buffer written
    Py_buffer &kept_stoppers = bufs[held];
    ok = ok && get_buffer(xo, &kept_stoppers, "q", 8, "stoppers", PyExc_TypeError, true) && ++held;
    Py_ssize_t most = ok ? kept_stoppers.len / 16 : 0;
    int64_t *stoppers = ok ? static_cast<int64_t *>(kept_stoppers.buf) : nullptr;
    Py_ssize_t stopping = 0;
    while (stopping < most && stoppers[2 * stopping] >= 0) ++stopping;
    ok = ok && kept_stoppers.len == 16 * most && faces_of(s, stoppers, stopping);
    const int64_t *faces = ok ? static_cast<const int64_t *>(bufs[5].buf) : nullptr;
    ok = ok && faces_of(s, faces, k);
    const double *expected_ = ok ? static_cast<const double *>(bufs[2].buf) : nullptr;
    for (Py_ssize_t i = 0; ok && i < m; ++i) ok = std::isfinite(expected_[i]);
    if (ok && (!(standoff > 0.0) || !std::isfinite(standoff) || !(deepest >= 0.0) || count < 0 || start < 0 ||
               cap < 0 || !(keep >= 0.0) || !(near_window >= 0.0) || !(wide_window >= 0.0) || std::isnan(reach)))
        ok = false;
    if (!ok) {
        if (!PyErr_Occurred())
            PyErr_SetString(PyExc_ValueError, "measure: poses (m, 4, 4), needed and finite expected (m,), gaps "
                                              "(k,), slopes (k, 3), faces (k, 2) and seeds (c, 2) of face "
                                              "indices, moves (m, 3), shift (3,), bounds (7,), stoppers (s, 2) "
                                              "of face indices up to the first -1; standoff positive; windows, "
                                              "count, deepest, start, cap and keep not negative, reach a number");
        for (int i = 0; i < held; ++i) PyBuffer_Release(&bufs[i]);
        return nullptr;
    }
    const double *p = static_cast<const double *>(bufs[0].buf), *needed = static_cast<const double *>(bufs[1].buf),
                 *expected = static_cast<const double *>(bufs[2].buf), *gaps = static_cast<const double *>(bufs[3].buf),
                 *slopes = static_cast<const double *>(bufs[4].buf), *moves = static_cast<const double *>(bufs[6].buf),
                 *shift = static_cast<const double *>(bufs[7].buf), *bounds = static_cast<const double *>(bufs[8].buf);
    std::vector<std::pair<double, int32_t>> ranked;
    std::vector<int64_t> picked;
    std::vector<int32_t> vertices, stack;
    long queries = 0;
    Measured kind = kShort;
    s.keep = keep;
    Py_ssize_t i = start;
    bool wide = false;
    for (; i < m; ++i) {
        if (std::isnan(needed[i]) || needed[i] == kInf) continue;
        // the pose's lateral offset from where the pool was taken, and whether that is
        // beyond its reach (the pool then names too little of what closes first there: a
        // place found is measured with the wide window, to become the pool)
        double offset[3];
        for (int j = 0; j < 3; ++j) offset[j] = moves[3 * i + j] + shift[j];
        wide = std::max(std::max(std::fabs(offset[0]), std::fabs(offset[1])), std::fabs(offset[2])) > reach;
        const double window = wide ? wide_window : near_window;
        const int64_t *from = seeds;
        Py_ssize_t from_count = c;
        if (count > 0) {
            s.place(p + 16 * i);
            if (stoppers_short(s, stoppers, stopping, needed[i], standoff, vertices) ||
                witness_short(s, gaps, slopes, faces, k, offset, count, needed[i], standoff, deepest, ranked,
                              picked, vertices, stack))
                continue;
            // the search starts from the stoppers too: a tighter bound from its first visit
            picked.insert(picked.end(), stoppers, stoppers + 2 * stopping);
            from = picked.data();
            from_count = static_cast<Py_ssize_t>(picked.size() / 2);
        }
        // a window that reaches no further than what is kept whole needs no cap
        s.cap = window > keep ? static_cast<size_t>(cap) : 0;
        kind = arrive(s, p + 16 * i, expected[i], needed[i], window, standoff, bounds, from, from_count, queries);
        if (kind != kShort) break;
        // the pair that stopped this search short, asked of the later poses first
        if (count > 0 && most > 0 && s.stopper[0] >= 0) remember_stopper(stoppers, stopping, most, s.stopper);
    }
    for (int j = 0; j < held; ++j) PyBuffer_Release(&bufs[j]);
    std::vector<Feature> kept;
    if (i < m && kind == kPlace) kept = kept_features(s);
    static const char nothing = 0;
    return Py_BuildValue("(nidy#llN)", std::min(i, m), static_cast<int>(i < m ? kind : kShort),
                         i < m && kind == kPlace ? s.best : -kInf,
                         kept.empty() ? &nothing : reinterpret_cast<const char *>(kept.data()),
                         static_cast<Py_ssize_t>(kept.size() * sizeof(Feature)), queries, s.pairs,
                         PyBool_FromLong(i < m && wide));
}

PyMethodDef module_methods[] = {
    {"first_unrefuted", first_unrefuted, METH_VARARGS,
     "first_unrefuted(fixed_view, moving_view, poses, needed, gaps, slopes, faces, offsets, count, behind, "
     "deepest, start) -> (index, witnesses)"},
    {"measure", measure, METH_VARARGS,
     "measure(fixed_view, moving_view, poses, needed, expected, near_window, wide_window, reach, gaps, slopes, "
     "faces, moves, shift, count, standoff, deepest, bounds, start, seeds, cap, keep, stoppers) -> (index, kind, "
     "travel, features, queries, pairs, wide)"},
    {"travels", travels, METH_VARARGS,
     "travels(fixed_view, moving_view, poses, behind, window, limit[, short_of]) -> (travels, buried, pairs)"},
    {"contacts", contacts, METH_VARARGS,
     "contacts(fixed_view, moving_view, pose, behind, window, limit[, short_of[, seeds]]) -> (travel, buried, features, pairs)"},
    {nullptr, nullptr, 0, nullptr}};

PyModuleDef module_def = {PyModuleDef_HEAD_INIT, "_sweep",
                          "Exact travel of a triangle mesh along a direction onto another.", -1,
                          module_methods};

}  // namespace

PyMODINIT_FUNC PyInit__sweep() {
    BodyType.tp_name = "kneeseat_core.meshes._sweep.Body";
    BodyType.tp_doc = "Body(vertices, faces, facing): a mesh and its hierarchy";
    BodyType.tp_basicsize = sizeof(PyBody);
    BodyType.tp_flags = Py_TPFLAGS_DEFAULT;
    BodyType.tp_new = PyType_GenericNew;
    BodyType.tp_init = reinterpret_cast<initproc>(body_init);
    BodyType.tp_dealloc = reinterpret_cast<destructor>(body_dealloc);
    ViewType.tp_name = "kneeseat_core.meshes._sweep.View";
    ViewType.tp_doc = "View(body, direction, side): a body seen along a direction";
    ViewType.tp_basicsize = sizeof(PyView);
    ViewType.tp_flags = Py_TPFLAGS_DEFAULT;
    ViewType.tp_new = PyType_GenericNew;
    ViewType.tp_init = reinterpret_cast<initproc>(view_init);
    ViewType.tp_dealloc = reinterpret_cast<destructor>(view_dealloc);
    ViewType.tp_methods = view_methods;
    if (PyType_Ready(&BodyType) < 0 || PyType_Ready(&ViewType) < 0) return nullptr;
    PyObject *m = PyModule_Create(&module_def);
    if (!m) return nullptr;
    Py_INCREF(&BodyType);
    Py_INCREF(&ViewType);
    if (PyModule_AddObject(m, "Body", reinterpret_cast<PyObject *>(&BodyType)) < 0 ||
        PyModule_AddObject(m, "View", reinterpret_cast<PyObject *>(&ViewType)) < 0) {
        Py_DECREF(m);
        return nullptr;
    }
    return m;
}
