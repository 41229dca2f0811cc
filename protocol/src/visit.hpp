// std::visit may throw bad_variant_access (never, for our variants, but the compiler and
// clang-tidy cannot know). This visitor cannot: it dispatches on index() with get_if.
#pragma once

#include <cstddef>
#include <utility>
#include <variant>

namespace mrskin::protocol::detail {

template <class R, class F, class V, std::size_t... I>
R visit_nothrow_impl(F&& f, V& v, std::index_sequence<I...> /*indices*/) noexcept {
  R result{};
  (void)((v.index() == I ? (result = f(*std::get_if<I>(&v)), true) : false) || ...);
  return result;
}

// Calls f on the active alternative of v; f must return R for every alternative.
template <class R, class F, class V>
R visit_nothrow(F&& f, V& v) noexcept {
  return visit_nothrow_impl<R>(std::forward<F>(f), v,
                               std::make_index_sequence<std::variant_size_v<std::remove_const_t<V>>>{});
}

}  // namespace mrskin::protocol::detail
