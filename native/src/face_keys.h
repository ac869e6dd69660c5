// Sorted face-key sets of one optimisation phase (dmesh/candidates.py): a face is the sorted triple
// (a, b, c) of point ids, its key (a * n + b) * n + c (dmesh.wdt.face_keys). Linear merges of sorted runs,
// where NumPy needs a binary search per key and several passes over the arrays.
#pragma once
#include <cstdint>
#include <vector>

#include "types.h"

namespace dmesh {

using face_key_t = std::int64_t;

// Sorted union of two sorted arrays of unique keys (the result is unique too).
std::vector<face_key_t> union_sorted_keys(const face_key_t* a, std::int64_t na, const face_key_t* b, std::int64_t nb);

struct OffWdtCandidates {
  std::vector<std::int64_t> faces;  // (C', 3) sorted triples
  std::vector<face_key_t> keys;          // (C',) their keys, ascending
};

// The candidates (sorted unique keys over n points) that are not WDT faces (`wdt`, sorted, may repeat) and
// whose three points are all not `hidden` (n flags).
OffWdtCandidates off_wdt_candidates(const face_key_t* cand, std::int64_t nc, const face_key_t* wdt, std::int64_t nw,
                                    const std::uint8_t* hidden, std::int64_t n);

}  // namespace dmesh
