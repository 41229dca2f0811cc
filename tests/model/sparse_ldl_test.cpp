// The network's sparse LDL^T (driver/src/model/network_ldl.cpp, compiled in again: it is private
// to the driver): the pass that skips exact zeros gives the bits of the full pass.
#include <gtest/gtest.h>

#include <bit>
#include <cstdint>
#include <random>
#include <string>
#include <vector>

#include "network_ldl.hpp"

namespace {

using mrskin::model::detail::SparseLdl;

// A grid of side x side nodes, 4-neighbour links, plus a hub linked to every node: the shape of
// a skin's cells and its reservoir. Each link conducts with probability `open`, else exactly 0.
struct Network {
  std::size_t n = 0;
  std::vector<SparseLdl::Pair> pairs;
  std::vector<double> conductance;
  std::vector<double> compliance;
};

Network make_network(std::size_t side, double open, std::uint64_t seed) {
  Network net;
  net.n = side * side + 1;
  const auto hub = static_cast<std::uint32_t>(side * side);
  for (std::uint32_t r = 0; r < side; ++r) {
    for (std::uint32_t c = 0; c < side; ++c) {
      const std::uint32_t i = r * static_cast<std::uint32_t>(side) + c;
      if (c + 1 < side) {
        net.pairs.emplace_back(i, i + 1);
      }
      if (r + 1 < side) {
        net.pairs.emplace_back(i, i + static_cast<std::uint32_t>(side));
      }
      net.pairs.emplace_back(i, hub);
    }
  }
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  for (std::size_t k = 0; k < net.pairs.size(); ++k) {
    net.conductance.push_back(unit(rng) < open ? 1e-3 + unit(rng) : 0.0);
  }
  for (std::size_t i = 0; i < net.n; ++i) {
    net.compliance.push_back(1e-4 + 1e-3 * unit(rng));
  }
  return net;
}

// M = diag(c) + B^T G B, written as the network writes it.
void assemble(SparseLdl& ldl, const Network& net) {
  const std::span<double> a = ldl.values();
  std::fill(a.begin(), a.end(), 0.0);
  for (std::size_t i = 0; i < net.n; ++i) {
    a[ldl.diagonal_slot(i)] += net.compliance[i];
  }
  for (std::size_t k = 0; k < net.pairs.size(); ++k) {
    a[ldl.diagonal_slot(net.pairs[k].first)] += net.conductance[k];
    a[ldl.diagonal_slot(net.pairs[k].second)] += net.conductance[k];
    a[ldl.pair_slot(k)] -= net.conductance[k];
  }
}

std::vector<double> right_hand_side(std::size_t n, std::uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> normal(0.0, 1.0);
  std::vector<double> b(n);
  for (double& v : b) {
    v = normal(rng);
  }
  return b;
}

// Equal as numbers, and the same bits unless zero (the skipping pass may flip a zero's sign).
void expect_same_bits(const std::vector<double>& a, const std::vector<double>& b) {
  ASSERT_EQ(a.size(), b.size());
  for (std::size_t i = 0; i < a.size(); ++i) {
    EXPECT_EQ(a[i], b[i]) << "entry " << i;
    if (a[i] != 0.0) {
      EXPECT_EQ(std::bit_cast<std::uint64_t>(a[i]), std::bit_cast<std::uint64_t>(b[i])) << "entry " << i;
    }
  }
}

class SparseLdlSkippingZeros : public ::testing::TestWithParam<double> {};

TEST_P(SparseLdlSkippingZeros, GivesTheFullPassBits) {
  for (const std::uint64_t seed : {1U, 2U, 3U}) {
    const Network net = make_network(12, GetParam(), seed);
    SparseLdl full(net.n, net.pairs);
    SparseLdl skipping(net.n, net.pairs);
    assemble(full, net);
    assemble(skipping, net);
    ASSERT_TRUE(full.factorize());
    ASSERT_TRUE(skipping.factorize_skipping_zeros());
    std::vector<double> x_full = right_hand_side(net.n, seed + 10);
    std::vector<double> x_skipping = x_full;
    full.solve(x_full);
    skipping.solve_skipping_zeros(x_skipping);
    expect_same_bits(x_full, x_skipping);
    // A right-hand side with zeros (the untouched nodes' residuals) too.
    for (std::size_t i = 0; i < net.n; i += 2) {
      x_full[i] = 0.0;
    }
    x_skipping = x_full;
    full.solve(x_full);
    skipping.solve_skipping_zeros(x_skipping);
    expect_same_bits(x_full, x_skipping);
  }
}

// Every passage locked, one in 20, one in 3, and every one open.
INSTANTIATE_TEST_SUITE_P(OpenFractions, SparseLdlSkippingZeros, ::testing::Values(0.0, 0.05, 0.3, 1.0));

// Most passages open: the pass keeps nearly all of L, and the next ones are full passes until it
// tries again; a network that locks up is then skipped again. The bits never change.
TEST(SparseLdlSkippingZeros, KeepsTheBitsAsTheNetworkOpensAndLocks) {
  const Network open = make_network(12, 1.0, 11);
  const Network locked = make_network(12, 0.05, 12);
  SparseLdl full(open.n, open.pairs);
  SparseLdl skipping(open.n, open.pairs);
  std::size_t kept_open = 0;
  std::size_t kept_locked = 0;
  for (int pass = 0; pass < 60; ++pass) {
    const Network& net = (pass / 20) % 2 == 0 ? open : locked;  // 20 open, 20 locked, 20 open
    assemble(full, net);
    assemble(skipping, net);
    ASSERT_TRUE(full.factorize());
    ASSERT_TRUE(skipping.factorize_skipping_zeros());
    if (pass == 0) {
      kept_open = skipping.kept_nonzeros();
    }
    if (pass == 39) {
      kept_locked = skipping.kept_nonzeros();
    }
    std::vector<double> x_full = right_hand_side(open.n, 100 + static_cast<std::uint64_t>(pass));
    std::vector<double> x_skipping = x_full;
    full.solve(x_full);
    skipping.solve_skipping_zeros(x_skipping);
    SCOPED_TRACE("pass " + std::to_string(pass));
    expect_same_bits(x_full, x_skipping);
  }
  // Every passage open keeps L's whole pattern; at one in 20 the locked pass (the last of the
  // locked ones, after the full passes ran out) kept a small part of it.
  EXPECT_EQ(kept_open, full.factor_nonzeros());
  EXPECT_GT(kept_locked, 0U);
  EXPECT_LT(kept_locked * 4, full.factor_nonzeros());
}

TEST(SparseLdlSkippingZeros, StandingAloneNodesSolveAsTheirDiagonal) {
  const Network net = make_network(6, 0.0, 4);
  SparseLdl ldl(net.n, net.pairs);
  assemble(ldl, net);
  ASSERT_TRUE(ldl.factorize_skipping_zeros());
  std::vector<double> x = right_hand_side(net.n, 5);
  const std::vector<double> b = x;
  ldl.solve_skipping_zeros(x);
  for (std::size_t i = 0; i < net.n; ++i) {
    EXPECT_EQ(x[i], b[i] / net.compliance[i]) << "node " << i;
  }
}

TEST(SparseLdlSkippingZeros, AfterAFullFactorisationItSolvesWithThatOne) {
  Network net = make_network(8, 0.3, 6);
  SparseLdl ldl(net.n, net.pairs);
  assemble(ldl, net);
  ASSERT_TRUE(ldl.factorize_skipping_zeros());
  net.conductance.assign(net.conductance.size(), 0.5);  // a different matrix, factorised in full
  assemble(ldl, net);
  ASSERT_TRUE(ldl.factorize());
  std::vector<double> x_full = right_hand_side(net.n, 7);
  std::vector<double> x_skipping = x_full;
  ldl.solve(x_full);
  ldl.solve_skipping_zeros(x_skipping);
  expect_same_bits(x_full, x_skipping);
}

TEST(SparseLdlSkippingZeros, RefusesAPivotThatIsNotPositive) {
  Network net = make_network(5, 0.3, 8);
  net.compliance[7] = -1.0;  // a node standing alone with a negative compliance
  for (std::size_t k = 0; k < net.pairs.size(); ++k) {
    if (net.pairs[k].first == 7 || net.pairs[k].second == 7) {
      net.conductance[k] = 0.0;
    }
  }
  SparseLdl ldl(net.n, net.pairs);
  assemble(ldl, net);
  EXPECT_FALSE(ldl.factorize());
  EXPECT_FALSE(ldl.factorize_skipping_zeros());
}

}  // namespace
