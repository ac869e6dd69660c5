#include <nanobind/nanobind.h>

#include <stdexcept>
#include <string>

#include "face_keys.h"
#include "numpy_out.h"

namespace nb = nanobind;
using namespace dmesh;
using namespace dmesh::bind;

namespace {

// Sortedness is checked here, once per call, in O(n): an unsorted input would silently give wrong sets.
void require_sorted(const char* fn, const char* name, const In<face_key_t>& a, bool strictly) {
  require(fn, name, a, -1, -1);
  const face_key_t* p = a.data();
  for (size_t i = 1; i < a.shape(0); ++i) {
    if (strictly ? p[i] <= p[i - 1] : p[i] < p[i - 1]) {
      throw std::invalid_argument(std::string(fn) + ": " + name + " must be sorted" +
                                  (strictly ? " and unique" : "") + " (position " + std::to_string(i) + ")");
    }
  }
}

}  // namespace

void bind_keys(nb::module_& m) {
  m.def(
      "union_sorted_keys",
      [](In<face_key_t> a, In<face_key_t> b) {
        require_sorted("union_sorted_keys", "a", a, true);
        require_sorted("union_sorted_keys", "b", b, true);
        std::vector<face_key_t> u;
        {
          nb::gil_scoped_release release;
          u = union_sorted_keys(a.data(), std::int64_t(a.shape(0)), b.data(), std::int64_t(b.shape(0)));
        }
        const size_t size = u.size();
        return to_numpy(std::move(u), {size});
      },
      nb::arg("a").noconvert(), nb::arg("b").noconvert(),
      "union_sorted_keys(a, b) -> (U,) int64: sorted union of two sorted unique int64 arrays.");

  m.def(
      "off_wdt_candidates",
      [](In<face_key_t> cand, In<face_key_t> wdt, In<std::uint8_t> hidden) {
        const char* fn = "off_wdt_candidates";
        require_sorted(fn, "cand", cand, true);
        require_sorted(fn, "wdt", wdt, false);
        require(fn, "hidden", hidden, -1, -1);
        const std::int64_t n = std::int64_t(hidden.shape(0));
        if (n >= (std::int64_t(1) << 21)) {
          throw std::invalid_argument(std::string(fn) + ": keys support fewer than 2**21 points, got " +
                                      std::to_string(n));
        }
        const std::int64_t nc = std::int64_t(cand.shape(0));
        if (nc && (cand.data()[0] < 0 || cand.data()[nc - 1] >= n * n * n)) {
          throw std::invalid_argument(std::string(fn) + ": candidate keys must lie in [0, n^3) for n = " +
                                      std::to_string(n) + " points");
        }
        OffWdtCandidates r;
        {
          nb::gil_scoped_release release;
          r = off_wdt_candidates(cand.data(), nc, wdt.data(), std::int64_t(wdt.shape(0)), hidden.data(), n);
        }
        const size_t c = r.keys.size();
        return nb::make_tuple(to_numpy(std::move(r.faces), {c, 3}), to_numpy(std::move(r.keys), {c}));
      },
      nb::arg("cand").noconvert(), nb::arg("wdt").noconvert(), nb::arg("hidden").noconvert(),
      "off_wdt_candidates(cand (C,) i64 sorted unique, wdt (F,) i64 sorted, hidden (n,) u8)\n"
      "    -> (faces (C',3) i64, keys (C',) i64): the candidates not in the WDT whose three points are not\n"
      "hidden, in key order.");
}
