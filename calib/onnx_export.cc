#include "calib/onnx_export.h"

#include <onnx/checker.h>
#include <onnx/defs/schema.h>
#include <onnx/onnx_pb.h>
#include <onnx/shape_inference/implementation.h>

#include <Eigen/Core>
#include <cstring>
#include <fstream>
#include <limits>
#include <stdexcept>
#include <string>

#include "base/hash.h"

namespace gs360 {
namespace {

constexpr int kIrVersion = 7;  // ONNX 1.8: opsets up to 13

void SetFloatTensorType(onnx::ValueInfoProto* value, const std::string& name, int columns) {
  value->set_name(name);
  auto* tensor = value->mutable_type()->mutable_tensor_type();
  tensor->set_elem_type(onnx::TensorProto_DataType_FLOAT);
  auto* shape = tensor->mutable_shape();
  shape->add_dim()->set_dim_param("N");
  shape->add_dim()->set_dim_value(columns);
}

// A float initializer from a double matrix, stored row-major ([rows, cols]) as raw little-endian
// bytes; a vector when `vector` is set.
void AddInitializer(onnx::GraphProto* graph, const std::string& name, const Eigen::MatrixXd& m,
                    bool vector) {
  onnx::TensorProto* t = graph->add_initializer();
  t->set_name(name);
  t->set_data_type(onnx::TensorProto_DataType_FLOAT);
  if (vector) {
    t->add_dims(m.size());
  } else {
    t->add_dims(m.rows());
    t->add_dims(m.cols());
  }
  std::string raw;
  raw.resize(static_cast<std::size_t>(m.size()) * sizeof(float));
  std::size_t offset = 0;
  for (Eigen::Index r = 0; r < m.rows(); ++r) {
    for (Eigen::Index c = 0; c < m.cols(); ++c) {
      const auto v = static_cast<float>(m(r, c));
      std::memcpy(raw.data() + offset, &v, sizeof(float));
      offset += sizeof(float);
    }
  }
  t->set_raw_data(std::move(raw));
}

onnx::NodeProto* AddNode(onnx::GraphProto* graph, const std::string& op, const std::string& name,
                         std::initializer_list<std::string> inputs, const std::string& output) {
  onnx::NodeProto* node = graph->add_node();
  node->set_op_type(op);
  node->set_name(name);
  for (const std::string& in : inputs) node->add_input(in);
  node->add_output(output);
  return node;
}

void AddIntAttribute(onnx::NodeProto* node, const std::string& name, std::int64_t value) {
  auto* attribute = node->add_attribute();
  attribute->set_name(name);
  attribute->set_type(onnx::AttributeProto_AttributeType_INT);
  attribute->set_i(value);
}

void AddMetadata(onnx::ModelProto& model, const std::string& key, const std::string& value) {
  auto* prop = model.add_metadata_props();
  prop->set_key(key);
  prop->set_value(value);
}

void CheckModelProto(const onnx::ModelProto& model) {
  try {
    onnx::checker::check_model(model);
    // check_model does not infer shapes (ONNX 1.12): run strict shape inference on a copy, which
    // catches layers whose shapes do not chain.
    onnx::ModelProto copy = model;
    onnx::shape_inference::InferShapes(copy, onnx::OpSchemaRegistry::Instance(),
                                       onnx::ShapeInferenceOptions(true, 1, false));
  } catch (const std::exception& e) {
    throw std::runtime_error(std::string("ONNX checker rejected the model: ") + e.what());
  }
}

}  // namespace

void OnnxExportOptions::Check() const {
  const auto require_name = [](const char* field, const std::string& value) {
    if (value.empty()) {
      throw std::invalid_argument(std::string("OnnxExportOptions.") + field + " is empty");
    }
  };
  require_name("model_name", model_name);
  require_name("gs360_version", gs360_version);
  require_name("input_name", input_name);
  require_name("output_name", output_name);
  if (input_name == output_name) {
    throw std::invalid_argument("OnnxExportOptions.output_name = '" + output_name +
                                "' equals input_name");
  }
  if (opset_version < 11 || opset_version > 13) {
    throw std::invalid_argument("OnnxExportOptions.opset_version = " +
                                std::to_string(opset_version) + " must be in [11, 13]");
  }
}

namespace {

// The layer shapes must chain: ONNX's Gemm shape inference does not compare the inner
// dimensions, so the checker would not catch this.
void CheckLayerShapes(const Mlp& mlp) {
  const auto& layers = mlp.layers();
  if (layers.size() + 1 != mlp.sizes().size()) {
    throw std::invalid_argument("ExportMlpToOnnx: " + std::to_string(layers.size()) +
                                " layers for " + std::to_string(mlp.sizes().size()) + " sizes");
  }
  for (std::size_t k = 0; k < layers.size(); ++k) {
    const int rows = mlp.sizes()[k + 1];
    const int cols = k == 0 ? mlp.first_layer_input_size() : mlp.sizes()[k];
    if (layers[k].weight.rows() != rows || layers[k].weight.cols() != cols ||
        layers[k].bias.size() != rows) {
      throw std::invalid_argument("ExportMlpToOnnx: layer " + std::to_string(k) + " has weight [" +
                                  std::to_string(layers[k].weight.rows()) + ", " +
                                  std::to_string(layers[k].weight.cols()) + "] and bias [" +
                                  std::to_string(layers[k].bias.size()) + "], sizes call for [" +
                                  std::to_string(rows) + ", " + std::to_string(cols) + "] and [" +
                                  std::to_string(rows) + "]");
    }
  }
}

// The Fourier features of tensor `current` as graph nodes; returns the features' tensor name.
std::string AddFourierNodes(onnx::GraphProto* graph, const FourierFeatures& fourier, int in,
                            const std::string& current) {
  // phases = a F^T with one non-zero per row of F (w_j at column i), so each phase is the
  // single float product w_j a_i that Mlp::Encode computes; then [a, sin, cos].
  const int count = fourier.inputs * fourier.frequencies;
  Eigen::MatrixXd f = Eigen::MatrixXd::Zero(count, in);
  for (int i = 0; i < fourier.inputs; ++i) {
    float w = fourier.base;
    for (int j = 0; j < fourier.frequencies; ++j, w *= 2.0f) {
      f(i * fourier.frequencies + j, i) = static_cast<double>(w);
    }
  }
  AddInitializer(graph, "fourier.frequencies", f, false);
  AddInitializer(graph, "fourier.zero", Eigen::VectorXd::Zero(count), true);
  onnx::NodeProto* phase =
      AddNode(graph, "Gemm", "fourier.Gemm", {current, "fourier.frequencies", "fourier.zero"},
              "fourier.phase");
  AddIntAttribute(phase, "transB", 1);
  AddNode(graph, "Sin", "fourier.Sin", {"fourier.phase"}, "fourier.sin");
  AddNode(graph, "Cos", "fourier.Cos", {"fourier.phase"}, "fourier.cos");
  onnx::NodeProto* concat = AddNode(graph, "Concat", "fourier.Concat",
                                    {current, "fourier.sin", "fourier.cos"}, "fourier.features");
  AddIntAttribute(concat, "axis", 1);
  return "fourier.features";
}

// The layers' Gemm and activation nodes after tensor `current`; the last layer's output is
// named `last_output` (empty: "layerN.gemm"). Returns the last tensor's name.
std::string AddLayerNodes(onnx::GraphProto* graph, const std::vector<Eigen::MatrixXd>& weights,
                          const std::vector<Eigen::VectorXd>& biases, Activation activation,
                          const std::string& last_output, std::string current) {
  const std::size_t num_layers = weights.size();
  for (std::size_t k = 0; k < num_layers; ++k) {
    const std::string prefix = "layer" + std::to_string(k);
    const bool last = k + 1 == num_layers;
    AddInitializer(graph, prefix + ".weight", weights[k], false);
    AddInitializer(graph, prefix + ".bias", biases[k], true);
    const std::string gemm_out = (last && !last_output.empty()) ? last_output : prefix + ".gemm";
    onnx::NodeProto* gemm = AddNode(graph, "Gemm", prefix + ".Gemm",
                                    {current, prefix + ".weight", prefix + ".bias"}, gemm_out);
    AddIntAttribute(gemm, "transB", 1);
    current = gemm_out;
    if (last) break;
    const std::string act_out = prefix + ".act";
    switch (activation) {
      case Activation::kTanh:
        AddNode(graph, "Tanh", prefix + ".Tanh", {current}, act_out);
        break;
      case Activation::kRelu:
        AddNode(graph, "Relu", prefix + ".Relu", {current}, act_out);
        break;
      case Activation::kSilu:
        AddNode(graph, "Sigmoid", prefix + ".Sigmoid", {current}, prefix + ".sigmoid");
        AddNode(graph, "Mul", prefix + ".Mul", {current, prefix + ".sigmoid"}, act_out);
        break;
    }
    current = act_out;
  }
  return current;
}

void AddModelMetadata(onnx::ModelProto& model, const Mlp& mlp, const OnnxExportOptions& options,
                      bool fold_input) {
  const std::vector<std::uint8_t> mlp_bytes = mlp.Serialize();
  const FourierFeatures& fourier = mlp.fourier();
  AddMetadata(model, "gs360_version", options.gs360_version);
  AddMetadata(model, "model_name", options.model_name);
  AddMetadata(model, "input_description", options.input_description);
  AddMetadata(model, "output_description", options.output_description);
  AddMetadata(model, "activation", std::string(ToString(mlp.activation())));
  AddMetadata(model, "normalization",
              fold_input
                  ? "folded"
                  : (options.fold_normalization ? "input explicit, output folded" : "explicit"));
  AddMetadata(model, "fourier_features",
              std::to_string(fourier.inputs) + " inputs x " + std::to_string(fourier.frequencies) +
                  " frequencies, base " + std::to_string(fourier.base) +
                  " rad per normalised unit");
  AddMetadata(model, "mlp_checksum", HashHex(mlp_bytes.data(), mlp_bytes.size()));
}

}  // namespace

std::vector<std::uint8_t> ExportMlpToOnnx(const Mlp& mlp, const OnnxExportOptions& options) {
  GOOGLE_PROTOBUF_VERIFY_VERSION;
  options.Check();
  const auto& layers = mlp.layers();
  if (mlp.sizes().empty() || layers.empty()) {
    throw std::invalid_argument("ExportMlpToOnnx: empty network");
  }
  const int in = mlp.input_size();
  const int out = mlp.output_size();
  CheckLayerShapes(mlp);
  const std::size_t num_layers = layers.size();
  std::vector<Eigen::MatrixXd> weights(num_layers);
  std::vector<Eigen::VectorXd> biases(num_layers);
  for (std::size_t k = 0; k < num_layers; ++k) {
    weights[k] = layers[k].weight.cast<double>();
    biases[k] = layers[k].bias.cast<double>();
  }
  const Eigen::VectorXd in_mean = mlp.input_mean().cast<double>();
  const Eigen::VectorXd in_scale = mlp.input_scale().cast<double>();
  const Eigen::VectorXd out_mean = mlp.output_mean().cast<double>();
  const Eigen::VectorXd out_scale = mlp.output_scale().cast<double>();
  // With Fourier features the first layer needs the normalised position for the phases, so the
  // input normalisation stays explicit; only the output's is folded.
  const FourierFeatures& fourier = mlp.fourier();
  const bool fold_input = options.fold_normalization && !fourier.Enabled();
  if (fold_input) {
    weights.front() = weights.front() * in_scale.cwiseInverse().asDiagonal();
    biases.front() = biases.front() - weights.front() * in_mean;
  }
  if (options.fold_normalization) {
    weights.back() = out_scale.asDiagonal() * weights.back();
    biases.back() = out_scale.cwiseProduct(biases.back()) + out_mean;
  }

  onnx::ModelProto model;
  model.set_ir_version(kIrVersion);
  model.set_producer_name("gs360");
  model.set_producer_version(options.gs360_version);
  model.set_domain("org.gs360");
  model.set_model_version(1);
  model.set_doc_string("gs360 tactile calibration MLP: " + options.input_description + " -> " +
                       options.output_description);
  auto* opset = model.add_opset_import();
  opset->set_domain("");
  opset->set_version(options.opset_version);

  onnx::GraphProto* graph = model.mutable_graph();
  graph->set_name(options.model_name);
  SetFloatTensorType(graph->add_input(), options.input_name, in);
  SetFloatTensorType(graph->add_output(), options.output_name, out);

  std::string current = options.input_name;
  if (!fold_input) {
    AddInitializer(graph, "input_mean", in_mean, true);
    AddInitializer(graph, "input_scale", in_scale, true);
    AddNode(graph, "Sub", "normalize_sub", {current, "input_mean"}, "input_centered");
    AddNode(graph, "Div", "normalize_div", {"input_centered", "input_scale"}, "input_normalized");
    current = "input_normalized";
  }
  if (fourier.Enabled()) current = AddFourierNodes(graph, fourier, in, current);
  current = AddLayerNodes(graph, weights, biases, mlp.activation(),
                          options.fold_normalization ? options.output_name : "", current);
  if (!options.fold_normalization) {
    AddInitializer(graph, "output_scale", out_scale, true);
    AddInitializer(graph, "output_mean", out_mean, true);
    AddNode(graph, "Mul", "denormalize_mul", {current, "output_scale"}, "output_scaled");
    AddNode(graph, "Add", "denormalize_add", {"output_scaled", "output_mean"}, options.output_name);
  }

  AddModelMetadata(model, mlp, options, fold_input);

  CheckModelProto(model);
  std::string bytes;
  if (!model.SerializeToString(&bytes)) {
    throw std::runtime_error("ExportMlpToOnnx: protobuf serialisation failed");
  }
  return std::vector<std::uint8_t>(bytes.begin(), bytes.end());
}

void WriteOnnxFile(const std::filesystem::path& path, const Mlp& mlp,
                   const OnnxExportOptions& options) {
  const std::vector<std::uint8_t> bytes = ExportMlpToOnnx(mlp, options);
  std::ofstream file(path, std::ios::binary | std::ios::trunc);
  if (!file) throw std::runtime_error("WriteOnnxFile: cannot open " + path.string());
  file.write(reinterpret_cast<const char*>(bytes.data()),
             static_cast<std::streamsize>(bytes.size()));
  file.close();
  if (!file) throw std::runtime_error("WriteOnnxFile: cannot write " + path.string());
}

void CheckOnnxModel(std::span<const std::uint8_t> bytes) {
  GOOGLE_PROTOBUF_VERIFY_VERSION;
  onnx::ModelProto model;
  if (bytes.size() > static_cast<std::size_t>(std::numeric_limits<int>::max()) ||
      !model.ParseFromArray(bytes.data(), static_cast<int>(bytes.size()))) {
    throw std::runtime_error("CheckOnnxModel: cannot parse " + std::to_string(bytes.size()) +
                             " bytes as an ONNX ModelProto");
  }
  CheckModelProto(model);
}

}  // namespace gs360
