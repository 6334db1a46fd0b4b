#pragma once
// Options structs described once, field by field, so that code can walk them: into JSON (cache
// keys, reports) and, in tests, with every field changed in turn.
//
// A struct opts in with a static member template that names every field:
//
//   struct RenderOptions {
//     double margin_px = 2.0;
//     double max_slope_deg = 80.0;
//     template <typename Self, typename Visitor>
//     static void Fields(Self& self, Visitor& visit) {
//       visit("margin_px", self.margin_px);
//       visit("max_slope_deg", self.max_slope_deg);
//     }
//   };
//
// `Self` is the struct or its const form. A static member function keeps the struct an
// aggregate, so AggregateFieldCount<T>() can count its members at compile time; a test compares
// that count with NamedFieldCount<T>(), so a member added to the struct and not to Fields() is
// caught.
//
// Leaves: bool, integers, floating point, enums (as their underlying integer), std::string,
// std::filesystem::path and std::vector of leaves. A member whose type has Fields() is a nested
// object.

#include <cstddef>
#include <filesystem>
#include <string>
#include <type_traits>
#include <utility>
#include <vector>

#include <nlohmann/json.hpp>

namespace gs360 {
namespace fields_detail {

struct NameOnly {
  template <typename T>
  void operator()(const char*, T&) {}
};

}  // namespace fields_detail

template <typename T>
concept Described = requires(T& t, fields_detail::NameOnly& v) {
  T::Fields(t, v);
};

namespace fields_detail {

// Converts to a reference to anything: T{AnyField, ...} compiles for as many of them as T has
// members (and no more, since no brace elision happens when every initialiser converts).
struct AnyField {
  template <typename T>
  constexpr operator T&() const&& noexcept;
};
template <std::size_t>
using AnyFieldAt = AnyField;

template <typename T, std::size_t... I>
constexpr bool InitializableWith(std::index_sequence<I...>) {
  return requires {
    T{AnyFieldAt<I>{}...};
  };
}

template <typename T>
struct IsVector : std::false_type {};
template <typename T, typename A>
struct IsVector<std::vector<T, A>> : std::true_type {};

struct Counter {
  std::size_t count = 0;
  template <typename T>
  void operator()(const char*, const T&) {
    ++count;
  }
};

template <typename T>
nlohmann::json LeafToJson(const T& v) {
  if constexpr (Described<T>) {
    nlohmann::json object = nlohmann::json::object();
    auto visit = [&object](const char* name, const auto& field) {
      object[name] = LeafToJson(field);
    };
    T::Fields(v, visit);
    return object;
  } else if constexpr (IsVector<T>::value) {
    nlohmann::json array = nlohmann::json::array();
    for (const auto& e : v) array.push_back(LeafToJson(e));
    return array;
  } else if constexpr (std::is_enum_v<T>) {
    return static_cast<std::underlying_type_t<T>>(v);
  } else if constexpr (std::is_same_v<T, std::filesystem::path>) {
    return v.string();
  } else {
    static_assert(std::is_arithmetic_v<T> || std::is_same_v<T, std::string>,
                  "a field of a Described struct must be a leaf or Described");
    return v;
  }
}

// A different value of the same type (for tests that change one field at a time).
template <typename T>
void Change(T& v) {
  if constexpr (IsVector<T>::value) {
    v.emplace_back();
  } else if constexpr (std::is_enum_v<T>) {
    v = static_cast<T>(static_cast<std::underlying_type_t<T>>(v) + 1);
  } else if constexpr (std::is_same_v<T, bool>) {
    v = !v;
  } else if constexpr (std::is_floating_point_v<T>) {
    v = v == T(0) ? T(1) : v * T(2);
  } else if constexpr (std::is_arithmetic_v<T>) {
    v = static_cast<T>(v + 1);
  } else if constexpr (std::is_same_v<T, std::filesystem::path>) {
    v /= "changed";
  } else {
    v += "-changed";
  }
}

// Changes the target-th leaf (depth first, in Fields() order) and records its dotted name.
struct LeafChanger {
  std::size_t target = 0;
  std::size_t index = 0;
  std::string prefix;
  std::string changed;
  template <typename T>
  void operator()(const char* name, T& field) {
    if constexpr (Described<T>) {
      const std::string saved = prefix;
      prefix += std::string(name) + ".";
      T::Fields(field, *this);
      prefix = saved;
    } else {
      if (index++ == target) {
        Change(field);
        changed = prefix + name;
      }
    }
  }
};

}  // namespace fields_detail

// The number of members of aggregate T (up to 64), at compile time.
template <typename T, std::size_t N = 0>
constexpr std::size_t AggregateFieldCount() {
  static_assert(std::is_aggregate_v<T>, "AggregateFieldCount needs an aggregate");
  if constexpr (N > 64) {
    return N;
  } else if constexpr (!fields_detail::InitializableWith<T>(std::make_index_sequence<N + 1>{})) {
    return N;
  } else {
    return AggregateFieldCount<T, N + 1>();
  }
}

// The number of fields T::Fields names (its direct members, nested objects counted once).
template <Described T>
std::size_t NamedFieldCount() {
  T t{};
  fields_detail::Counter counter;
  T::Fields(t, counter);
  return counter.count;
}

// {"field": value, "nested": {...}} in Fields() order of names (nlohmann sorts keys).
template <Described T>
nlohmann::json FieldsToJson(const T& value) {
  return fields_detail::LeafToJson(value);
}

// The structs in T's tree (T itself and every nested Described member) whose member count
// differs from what their Fields() names: "<root>.train.fourier has 4 members, Fields() names 3".
// Empty when every member of every struct is named.
template <Described T>
std::vector<std::string> FieldsNotNamed(const std::string& root) {
  std::vector<std::string> out;
  const std::size_t members = AggregateFieldCount<T>(), named = NamedFieldCount<T>();
  if (members != named) {
    out.push_back(root + " has " + std::to_string(members) + " members, Fields() names " +
                  std::to_string(named));
  }
  T t{};
  auto visit = [&](const char* name, auto& field) {
    using F = std::remove_cvref_t<decltype(field)>;
    if constexpr (Described<F>) {
      for (std::string& s : FieldsNotNamed<F>(root + "." + name)) out.push_back(std::move(s));
    }
  };
  T::Fields(t, visit);
  return out;
}

// One copy of `base` per leaf field (depth first), with that leaf changed to another value of
// its type, and the leaf's dotted name ("train.fourier.base").
template <Described T>
std::vector<std::pair<std::string, T>> EachFieldChanged(const T& base) {
  std::vector<std::pair<std::string, T>> out;
  for (std::size_t target = 0;; ++target) {
    T copy = base;
    fields_detail::LeafChanger changer;
    changer.target = target;
    T::Fields(copy, changer);
    if (changer.changed.empty()) break;
    out.emplace_back(std::move(changer.changed), std::move(copy));
  }
  return out;
}

}  // namespace gs360
