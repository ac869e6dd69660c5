// Moving std::vector results into NumPy arrays without a copy.
#pragma once
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>

#include <initializer_list>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

namespace dmesh::bind {
namespace nb = nanobind;

template <class T>
using NumpyArray = nb::ndarray<nb::numpy, T>;

// Hands ownership of v to a NumPy array of the given shape (the product must equal v.size()).
template <class T>
NumpyArray<T> to_numpy(std::vector<T>&& v, std::initializer_list<size_t> shape) {
  auto* heap = new std::vector<T>(std::move(v));
  nb::capsule owner(heap, [](void* p) noexcept { delete static_cast<std::vector<T>*>(p); });
  return NumpyArray<T>(heap->data(), shape, owner);
}

// Contiguous read-only CPU input arrays of a fixed dtype; `noconvert` on the argument makes a mismatch
// raise instead of copying silently.
template <class T>
using In = nb::ndarray<const T, nb::c_contig, nb::device::cpu>;

// Checks that `a` has shape (rows, cols) (cols < 0: 1-D; rows < 0: any rows); the error names the
// function, the argument, the expected and the actual shape.
template <class T>
inline void require(const char* fn, const char* name, const In<T>& a, long rows, long cols) {
  const bool ok = cols < 0 ? a.ndim() == 1 : (a.ndim() == 2 && long(a.shape(1)) == cols);
  if (!ok || (rows >= 0 && long(a.shape(0)) != rows)) {
    std::string got = "(";
    for (size_t k = 0; k < a.ndim(); ++k) got += (k ? ", " : "") + std::to_string(a.shape(k));
    throw std::invalid_argument(std::string(fn) + ": " + name + " must have shape (" +
                                (rows >= 0 ? std::to_string(rows) : std::string("rows")) +
                                (cols >= 0 ? ", " + std::to_string(cols) : std::string(",")) + "), got " + got +
                                ")");
  }
}

}  // namespace dmesh::bind
