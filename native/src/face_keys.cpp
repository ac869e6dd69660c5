#include "face_keys.h"

#include <algorithm>
#include <iterator>

namespace dmesh {

std::vector<face_key_t> union_sorted_keys(const face_key_t* a, std::int64_t na, const face_key_t* b, std::int64_t nb) {
  std::vector<face_key_t> out;
  out.reserve(size_t(na + nb));
  std::set_union(a, a + na, b, b + nb, std::back_inserter(out));
  return out;
}

OffWdtCandidates off_wdt_candidates(const face_key_t* cand, std::int64_t nc, const face_key_t* wdt, std::int64_t nw,
                                    const std::uint8_t* hidden, std::int64_t n) {
  OffWdtCandidates r;
  r.keys.reserve(size_t(nc));
  r.faces.reserve(3 * size_t(nc));
  std::int64_t j = 0;
  for (std::int64_t i = 0; i < nc; ++i) {
    const face_key_t k = cand[i];
    while (j < nw && wdt[j] < k) ++j;
    if (j < nw && wdt[j] == k) continue;
    const std::int64_t a = k / (n * n), b = (k / n) % n, c = k % n;
    if (hidden[a] | hidden[b] | hidden[c]) continue;
    r.keys.push_back(k);
    r.faces.push_back(a);
    r.faces.push_back(b);
    r.faces.push_back(c);
  }
  return r;
}

}  // namespace dmesh
