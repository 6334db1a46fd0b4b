// base/fields.h: walking an options struct, and catching a member Fields() forgot.

#include <catch2/catch.hpp>

#include <cmath>
#include <set>
#include <stdexcept>

#include "base/field_error.h"
#include "base/fields.h"

using namespace gs360;

namespace {

enum class Mode { kA, kB };

struct Inner {
  double scale = 0.5;
  std::vector<int> widths = {4, 8};
  template <typename Self, typename Visitor>
  static void Fields(Self& self, Visitor& visit) {
    visit("scale", self.scale);
    visit("widths", self.widths);
  }
};

struct Outer {
  int count = 3;
  bool on = true;
  Mode mode = Mode::kA;
  std::string name = "x";
  std::filesystem::path dir;
  Inner inner;
  std::uint64_t seed = 0;
  void Check() const {}
  template <typename Self, typename Visitor>
  static void Fields(Self& self, Visitor& visit) {
    visit("count", self.count);
    visit("on", self.on);
    visit("mode", self.mode);
    visit("name", self.name);
    visit("dir", self.dir);
    visit("inner", self.inner);
    visit("seed", self.seed);
  }
};

// Fields() forgets `b`.
struct Forgetful {
  int a = 0;
  int b = 0;
  template <typename Self, typename Visitor>
  static void Fields(Self& self, Visitor& visit) {
    visit("a", self.a);
  }
};

struct HoldsForgetful {
  Forgetful nested;
  template <typename Self, typename Visitor>
  static void Fields(Self& self, Visitor& visit) {
    visit("nested", self.nested);
  }
};

}  // namespace

TEST_CASE("fields: JSON of a described struct names every field", "[base][fields]") {
  const nlohmann::json j = FieldsToJson(Outer{});
  CHECK(j.at("count") == 3);
  CHECK(j.at("on") == true);
  CHECK(j.at("mode") == 0);
  CHECK(j.at("name") == "x");
  CHECK(j.at("dir") == "");
  CHECK(j.at("inner").at("scale") == 0.5);
  CHECK(j.at("inner").at("widths") == nlohmann::json::array({4, 8}));
  CHECK(j.size() == 7);
}

TEST_CASE("fields: member counts catch a field Fields() does not name", "[base][fields]") {
  STATIC_REQUIRE(AggregateFieldCount<Outer>() == 7);
  STATIC_REQUIRE(AggregateFieldCount<Inner>() == 2);
  CHECK(NamedFieldCount<Outer>() == 7);
  CHECK(FieldsNotNamed<Outer>("outer").empty());
  CHECK(NamedFieldCount<Forgetful>() == 1);
  const auto missing = FieldsNotNamed<HoldsForgetful>("root");
  REQUIRE(missing.size() == 1);
  CHECK(missing[0] == "root.nested has 2 members, Fields() names 1");
}

TEST_CASE("fields: each leaf changed in turn changes the JSON there only", "[base][fields]") {
  const Outer base;
  const nlohmann::json base_json = FieldsToJson(base);
  const auto changed = EachFieldChanged(base);
  std::set<std::string> names;
  for (const auto& [name, copy] : changed) {
    names.insert(name);
    const nlohmann::json j = FieldsToJson(copy);
    const nlohmann::json diff = nlohmann::json::diff(base_json, j);
    INFO(name << ": " << diff.dump());
    REQUIRE_FALSE(diff.empty());
    for (const auto& op : diff) {
      const std::string path = op.at("path").get<std::string>();
      std::string dotted = path.substr(1);
      for (char& c : dotted) c = c == '/' ? '.' : c;
      CHECK(dotted.rfind(name, 0) == 0);
    }
  }
  CHECK(names == std::set<std::string>{"count", "on", "mode", "name", "dir", "inner.scale",
                                       "inner.widths", "seed"});
}

TEST_CASE("fields: an invalid option names the field, the rule and the value", "[base][fields]") {
  CHECK(FieldErrorMessage("PoseOptions.huber_px", -1.0, "must be > 0") ==
        "PoseOptions.huber_px must be > 0, got -1");
  CHECK(FieldErrorMessage("a", 0.1, "r") == "a r, got 0.1");
  CHECK(FieldErrorMessage("a", std::nan(""), "r") == "a r, got nan");
  CHECK(FieldErrorMessage("a", -HUGE_VAL, "r") == "a r, got -inf");
  CHECK_THROWS_AS(ThrowFieldError("a", 1.0, "r"), std::invalid_argument);
}
