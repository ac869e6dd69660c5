// Loops over independent elements on several threads, for the kernels whose results must not depend on the
// thread count or schedule (every element is written by exactly one range; reductions happen elsewhere in a
// fixed order).
//
// TBB when compiled in (DMESH_HAVE_TBB), else OpenMP, else one thread. TBB because of how idle threads
// wait: an OpenMP (libgomp) thread that runs out of work spins for a long while (its default spin count is
// several milliseconds of `pause`) before it sleeps, both at the end of a parallel loop and while a
// statically scheduled sibling that the OS descheduled still works. On a machine whose cores are shared
// with other work, those spinning threads take CPU from the thread that still works and from whatever runs
// next (the triangulation's TBB threads, Python). TBB threads steal the remaining ranges instead of
// waiting at a barrier, and sleep soon after the work runs out. The probability pass runs a dozen such
// loops per step (issue 61: they took about a third of its time on a loaded 2-core machine).
#pragma once
#include <algorithm>
#include <cstddef>
#include <cstdint>

#ifdef DMESH_HAVE_TBB
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/partitioner.h>
#include <tbb/task_arena.h>
#endif
#ifdef _OPENMP
#include <omp.h>
#endif

namespace dmesh {

// The thread budget: OpenMP's maximum (which torch.set_num_threads sets), else TBB's default concurrency.
inline int thread_budget() {
#if defined(_OPENMP)
  return omp_get_max_threads();
#elif defined(DMESH_HAVE_TBB)
  return tbb::this_task_arena::max_concurrency();
#else
  return 1;
#endif
}

// Threads for a loop over `size` elements: num_threads > 0 forces that many; 0 uses the thread budget above
// `threshold` elements and one thread below.
inline int threads_for(int num_threads, std::size_t size, std::size_t threshold) {
  if (num_threads > 0) return num_threads;
  return size > threshold ? thread_budget() : 1;
}

// Calls body(lo, hi) on consecutive ranges [lo, hi) that cover [0, n), each at most `grain` long, on up to
// `threads` threads (one thread: a single call body(0, n)). Ranges run in any order and on any thread: the
// body writes only what belongs to its range. Per-range scratch is the body's to allocate.
template <class Body>
void parallel_ranges(std::int64_t n, std::int64_t grain, int threads, Body&& body) {
  if (n <= 0) return;
  grain = std::max<std::int64_t>(grain, 1);
  if (threads <= 1 || n <= grain) {
    body(std::int64_t(0), n);
    return;
  }
#if defined(DMESH_HAVE_TBB)
  tbb::task_arena arena(threads);
  arena.execute([&] {
    tbb::parallel_for(
        tbb::blocked_range<std::int64_t>(0, n, grain),
        [&](const tbb::blocked_range<std::int64_t>& r) { body(r.begin(), r.end()); }, tbb::simple_partitioner());
  });
#elif defined(_OPENMP)
  const std::int64_t chunks = (n + grain - 1) / grain;
#pragma omp parallel for schedule(dynamic, 1) num_threads(threads)
  for (std::int64_t c = 0; c < chunks; ++c) body(c * grain, std::min(n, (c + 1) * grain));
#else
  body(std::int64_t(0), n);
#endif
}

// A grain that splits n elements into about 8 ranges per thread, at least `least` elements each.
inline std::int64_t grain_for(std::int64_t n, int threads, std::int64_t least = 256) {
  return std::max<std::int64_t>(least, n / (8 * std::max(threads, 1)) + 1);
}

}  // namespace dmesh
