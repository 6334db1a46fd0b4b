// The gs360 Python module: an exported model (.gs360model) turns tactile frames into depth.
//
//   model = gs360.Model.load("run-3.gs360model")
//   depth, points, contacts = model.reconstruct(frame)   # frame: H x W x 3 uint8, BGR
//
// depth: H x W float32, the gel's indentation (mm, + into the gel) on the camera's pixel grid,
// 0 where there is no contact; points: N x 3 float32, the contact's surface (sensor frame, mm);
// contacts: a list of dicts (recon/contacts.h). The frame is read in place when it is a
// C-contiguous uint8 array (no copy); depth and points are handed over without a copy.
// Errors: ValueError for a frame of the wrong shape or type, RuntimeError for an unreadable
// model (the message names the file and the problem). A frame that cannot be reconstructed (it
// differs from the reference over more of the image than a contact could: saturated, black,
// corrupt, the lighting changed) gives no depth and a RuntimeWarning saying why.

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <memory>
#include <string>
#include <vector>

#include "base/version.h"
#include "recon/contacts.h"
#include "recon/model_bundle.h"

namespace py = pybind11;

namespace gs360 {
namespace {

using Frame = py::array_t<std::uint8_t, py::array::c_style>;

// A cv::Mat viewing a numpy frame (no copy); throws ValueError naming the expected shape.
cv::Mat View(const Frame& frame, int width, int height, const char* what) {
  if (frame.ndim() != 3 || frame.shape(0) != height || frame.shape(1) != width ||
      frame.shape(2) != 3) {
    std::string shape;
    for (py::ssize_t i = 0; i < frame.ndim(); ++i) {
      shape += (i ? ", " : "") + std::to_string(frame.shape(i));
    }
    throw py::value_error(std::string(what) + " must be a " + std::to_string(height) + " x " +
                          std::to_string(width) + " x 3 uint8 (BGR) array, got shape (" + shape +
                          ")");
  }
  return cv::Mat(height, width, CV_8UC3, const_cast<std::uint8_t*>(frame.data()));
}

// Hands `mat` to numpy without a copy: the array keeps the Mat alive.
template <typename T>
py::array_t<T> Give(cv::Mat mat, std::vector<py::ssize_t> shape) {
  auto* owner = new cv::Mat(std::move(mat));
  py::capsule free(owner, [](void* p) { delete static_cast<cv::Mat*>(p); });
  return py::array_t<T>(shape, reinterpret_cast<T*>(owner->data), free);
}

py::dict ContactDict(const ContactSummary& c) {
  const auto vec = [](const Eigen::Vector3d& v) { return py::make_tuple(v.x(), v.y(), v.z()); };
  py::dict d;
  d["centre_sensor_mm"] = vec(c.centre_sensor);
  d["peak_sensor_mm"] = vec(c.peak_sensor);
  d["peak_indentation_mm"] = c.peak_indentation_mm;
  d["area_mm2"] = c.area_mm2;
  d["pixels"] = c.pixels;
  d["partial"] = c.partial;
  d["roi"] = py::make_tuple(c.roi.x, c.roi.y, c.roi.width, c.roi.height);
  return d;
}

class Model {
 public:
  static std::shared_ptr<Model> Load(const std::string& path, int mlp_stride) {
    auto m = std::shared_ptr<Model>(new Model());
    ModelBundle bundle;
    try {
      bundle = ReadModelBundle(path);
    } catch (const ModelBundleError& e) {
      throw std::runtime_error(std::string(e.what()) +
                               ". Export the model again (`gs360 export RUN --out DIR`).");
    }
    bundle.reconstruction.mlp_stride = mlp_stride;
    m->name_ = bundle.name + "-" + bundle.version;
    m->recon_ = std::make_unique<Reconstructor>(bundle.MakeReconstructor(2));
    return m;
  }

  py::tuple Reconstruct(const Frame& frame, const py::object& reference,
                        double min_indentation_mm) const {
    const int w = recon_->map().width(), h = recon_->map().height();
    const cv::Mat image = View(frame, w, h, "frame");
    cv::Mat ref = recon_->reference();
    Frame ref_array;
    if (!reference.is_none()) {
      ref_array = reference.cast<Frame>();
      ref = View(ref_array, w, h, "reference");
    }
    FrameReconstruction r;
    {
      py::gil_scoped_release release;  // frames in flight on several Python threads
      r = recon_->Reconstruct(image, ref);
    }
    if (!r.problem.empty()) {
      // Not an error: the next frame may be fine. Raised when warnings are made errors.
      const std::string message = "gs360: frame not reconstructed: " + r.problem;
      if (PyErr_WarnEx(PyExc_RuntimeWarning, message.c_str(), 1) != 0) {
        throw py::error_already_set();
      }
    }
    const std::vector<ContactSummary> contacts = SummarizeContacts(*recon_, r, min_indentation_mm);
    const std::vector<Eigen::Vector3f> points = recon_->PointCloud(r, min_indentation_mm);
    cv::Mat cloud(static_cast<int>(points.size()), 3, CV_32F);
    for (std::size_t i = 0; i < points.size(); ++i) {
      for (int k = 0; k < 3; ++k) cloud.at<float>(static_cast<int>(i), k) = points[i][k];
    }
    py::list summary;
    for (const ContactSummary& c : contacts) summary.append(ContactDict(c));
    return py::make_tuple(Give<float>(IndentationImage(*recon_, r), {h, w}),
                          Give<float>(cloud, {static_cast<py::ssize_t>(points.size()), 3}),
                          summary);
  }

  std::string name() const { return name_; }
  py::tuple size() const { return py::make_tuple(recon_->map().width(), recon_->map().height()); }
  py::array_t<std::uint8_t> reference() const {
    return Give<std::uint8_t>(recon_->reference().clone(),
                              {recon_->map().height(), recon_->map().width(), 3});
  }

 private:
  Model() = default;
  std::string name_;
  std::unique_ptr<Reconstructor> recon_;
};

}  // namespace
}  // namespace gs360

PYBIND11_MODULE(gs360, m) {
  using gs360::Model;
  m.doc() = "gs360: tactile frames to depth with an exported GelSight360 model";
  m.attr("__version__") = std::string(gs360::Version());
  m.attr("__commit__") = std::string(gs360::Commit());
  py::class_<Model, std::shared_ptr<Model>>(m, "Model")
      .def_static("load", &Model::Load, py::arg("path"), py::arg("mlp_stride") = 2,
                  "Loads a .gs360model bundle (checked: format, checksum, every part)")
      .def("reconstruct", &Model::Reconstruct, py::arg("frame"), py::arg("reference") = py::none(),
           py::arg("min_indentation_mm") = 0.02,
           "frame (H x W x 3 uint8 BGR) -> (depth H x W float32 mm, points N x 3 float32 mm in "
           "the sensor frame, contacts: list of dicts); a frame that cannot be reconstructed "
           "(saturated, black, corrupt, the lighting changed) gives no depth and a "
           "RuntimeWarning saying why")
      .def_property_readonly("name", &Model::name)
      .def_property_readonly("size", &Model::size, "(width, height) of the camera")
      .def_property_readonly("reference", &Model::reference,
                             "the model's no-contact frame (H x W x 3 uint8 BGR)");
}
