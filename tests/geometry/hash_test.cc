#include <catch2/catch.hpp>

#include <string>

#include "geometry/hash.h"

TEST_CASE("Hasher is deterministic and sensitive to every byte", "[hash]") {
  std::string data(1000, 'x');
  const std::string h0 = gs360::HashHex(data.data(), data.size());
  CHECK(h0.size() == 16);
  CHECK(h0 == gs360::HashHex(data.data(), data.size()));
  for (std::size_t i : {0u, 7u, 8u, 500u, 999u}) {
    std::string changed = data;
    changed[i] = 'y';
    CHECK(gs360::HashHex(changed.data(), changed.size()) != h0);
  }
  CHECK(gs360::HashHex(data.data(), 999) != h0);
}

TEST_CASE("Hasher separates strings and folds signed zero", "[hash]") {
  CHECK(gs360::Hasher().Add("ab").Add("c").Hex() != gs360::Hasher().Add("a").Add("bc").Hex());
  CHECK(gs360::Hasher().AddDouble(0.0).Hex() == gs360::Hasher().AddDouble(-0.0).Hex());
  CHECK(gs360::Hasher().AddDouble(1.0).Hex() != gs360::Hasher().AddDouble(1.0 + 1e-15).Hex());
}
