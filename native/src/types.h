// Array element types shared by every kernel and binding (STYLE rule 4).
//
// Geometry that decides combinatorics (positions, weights, orthocentres) is float64; indices are int32
// (a triangulation of 2^31 tets does not fit in memory here anyway). -1 is the only "none" index.
#pragma once
#include <cstdint>

namespace dmesh {
using real_t = double;      // positions, weights, orthocentres
using index_t = std::int32_t;
constexpr index_t kNone = -1;
}  // namespace dmesh
