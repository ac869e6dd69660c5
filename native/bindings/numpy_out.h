// Moving std::vector results into NumPy arrays without a copy.
#pragma once
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>

#include <initializer_list>
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

}  // namespace dmesh::bind
