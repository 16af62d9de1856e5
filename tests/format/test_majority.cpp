// The one majority rule (format core, downsample.h), used by the label pyramid and by the
// pipeline's pack.downsample: pins its tie-break for small (pairwise) and large (sorted) inputs.
#include <gtest/gtest.h>

#include <algorithm>
#include <map>
#include <random>
#include <vector>

#include "vispack/format/downsample.h"

using vispack::format::reduce_majority;

namespace {

// The rule spelled out: highest count; ties to a non-zero ID over 0, then to the smallest.
std::uint16_t reference(const std::vector<std::uint16_t>& ids) {
  std::map<std::uint16_t, int> count;
  for (auto id : ids)
    ++count[id];
  int best_n = 0;
  for (const auto& [id, n] : count)
    best_n = std::max(best_n, n);
  std::vector<std::uint16_t> tied;
  for (const auto& [id, n] : count)
    if (n == best_n) tied.push_back(id);  // ascending
  if (tied.size() > 1 && tied.front() == 0) return tied[1];
  return tied.front();
}

std::uint16_t majority(const std::vector<std::uint16_t>& ids) {
  return reduce_majority(ids.data(), ids.size());
}

TEST(Majority, TieBreakNonZeroOverZeroThenSmallest) {
  // 2x2x2 children (the pairwise path).
  EXPECT_EQ(majority({0, 0, 0, 0, 5, 5, 5, 5}), 5) << "a tie with 0 goes to the label";
  EXPECT_EQ(majority({7, 7, 3, 3}), 3) << "a tie between labels goes to the smaller ID";
  EXPECT_EQ(majority({3, 7, 7, 3, 0, 0}), 3);
  EXPECT_EQ(majority({0, 0, 0, 5, 5}), 0) << "0 wins when it is strictly the most frequent";
  EXPECT_EQ(majority({9}), 9);
  EXPECT_EQ(majority({0}), 0);
  // f x f blocks of pack.downsample (the sorted path, more than 8 IDs).
  std::vector<std::uint16_t> block(16, 0);
  std::fill(block.begin() + 8, block.end(), 12);
  EXPECT_EQ(majority(block), 12) << "4x4 block: 8 gel, 8 label 12";
  std::vector<std::uint16_t> two(36);
  for (std::size_t i = 0; i < two.size(); ++i)
    two[i] = i % 2 ? 40 : 41;
  EXPECT_EQ(majority(two), 40) << "6x6 block: 18 x 41, 18 x 40";
  std::vector<std::uint16_t> zero_wins(25, 0);
  std::fill(zero_wins.begin(), zero_wins.begin() + 12, 3);
  EXPECT_EQ(majority(zero_wins), 0) << "5x5 block: 13 gel beat 12 label 3";
}

TEST(Majority, BothPathsFollowTheRuleOnRandomBlocks) {
  std::mt19937 rng(2024);
  for (int trial = 0; trial < 20000; ++trial) {
    const std::size_t n = std::uniform_int_distribution<std::size_t>(1, trial % 3 ? 8 : 64)(rng);
    std::uniform_int_distribution<int> pick(0, trial % 2 ? 3 : 40);
    std::vector<std::uint16_t> ids(n);
    for (auto& id : ids)
      id = std::uint16_t(pick(rng));
    ASSERT_EQ(majority(ids), reference(ids)) << "trial " << trial << ", " << n << " IDs";
  }
}

}  // namespace
