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
// Loops over fewer elements than this run on one thread: OpenMP start-up and barriers cost more than the
// work, and much more on a loaded machine where idle threads spin.
constexpr index_t kParallelMin = 20000;
}  // namespace dmesh
