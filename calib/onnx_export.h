#pragma once
// Calibration stage "export" (ONNX part): the trained MLP as an ONNX model for Python users
// (onnxruntime, OpenCV's dnn module, ...).
//
// Graph (opset 13 by default, IR version 7), one sample per ROW, unlike Mlp::Forward:
//   input  "input"  float [N, in]   raw features, as given to Mlp::Forward (u, v in px, then the
//                                   normalised colour change dR, dG, dB)
//   with Fourier features (recon/mlp.h): phases = Gemm(normalised input, frequencies), then
//   Concat(normalised input, Sin(phases), Cos(phases)) is the first layer's input;
//   Gemm(transB = 1, weights stored [out, in]) + activation per hidden layer, a final Gemm
//   output "slopes" float [N, out]  tangent-frame slopes (gx, gy), de-normalised
// Activations: Tanh, Relu, and silu as x * Sigmoid(x) (Sigmoid + Mul); all are handled by
// OpenCV 4.6's ONNX importer.
//
// Normalisation: by default FOLDED into the first and last Gemm (computed in double, stored as
// float): W0' = W0 diag(1 / input_scale), b0' = b0 - W0' input_mean, W_last' =
// diag(output_scale) W_last, b_last' = output_scale .* b_last + output_mean. The graph is then
// just Gemms and activations. With fold_normalization = false the graph has explicit Sub / Div
// nodes after the input and Mul / Add nodes before the output instead. With Fourier features the
// input's Sub / Div are always explicit (the phases need the normalised position).
//
// Metadata props: gs360_version, model_name, input_description, output_description,
// activation, normalization ("folded" / "explicit"), mlp_checksum (HashHex of Mlp::Serialize()).
//
// Every exported model passes onnx::checker::check_model and ONNX's strict shape inference;
// a failure throws std::runtime_error carrying the checker's message.

#include <cstdint>
#include <filesystem>
#include <span>
#include <string>
#include <vector>

#include "base/version.h"
#include "recon/mlp.h"

namespace gs360 {

struct OnnxExportOptions {
  std::string model_name = "gs360_slopes_mlp";
  std::string gs360_version{Version()};  // written as producer_version and metadata
  std::string input_name = "input";
  std::string output_name = "slopes";
  std::string input_description =
      "per pixel: u, v (raw fisheye pixel, px), normalised colour change dR, dG, dB";
  std::string output_description =
      "per pixel: tangent-frame surface slopes gx = (n.t1)/(n.n0), gy = (n.t2)/(n.n0)";
  int opset_version = 13;  // 11..13 (what OpenCV 4.6's importer handles)
  bool fold_normalization = true;

  // Throws std::invalid_argument naming the field and its value.
  void Check() const;
};

// The serialized ModelProto. Throws std::invalid_argument for bad options, an empty Mlp or
// layer matrices that do not match mlp.sizes(); std::runtime_error if the ONNX checker rejects
// the model.
std::vector<std::uint8_t> ExportMlpToOnnx(const Mlp& mlp, const OnnxExportOptions& options = {});

// ExportMlpToOnnx, then writes the bytes to `path` (created or truncated). Throws
// std::runtime_error naming the path when it cannot be written.
void WriteOnnxFile(const std::filesystem::path& path, const Mlp& mlp,
                   const OnnxExportOptions& options = {});

// Parses a serialized ModelProto and runs onnx::checker::check_model plus strict shape
// inference. Throws std::runtime_error ("cannot parse" or the checker's message).
void CheckOnnxModel(std::span<const std::uint8_t> bytes);

}  // namespace gs360
