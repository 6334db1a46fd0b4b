#include "geometry/assimp_import.h"

#include <assimp/postprocess.h>
#include <assimp/scene.h>
#include <fcntl.h>
#include <poll.h>
#include <sys/wait.h>
#include <unistd.h>

#include <assimp/Importer.hpp>
#include <cerrno>
#include <chrono>
#include <csignal>
#include <cstdint>
#include <cstring>
#include <string>

#include "base/format.h"

namespace gs360::geometry_internal {
namespace {

// The child's reply: one tag byte, then the mesh (counts and arrays, native layout: both ends are
// this binary) or a message.
constexpr char kMeshReply = 'M';
constexpr char kErrorReply = 'E';

std::string Quoted(const std::filesystem::path& p) {
  return "'" + p.string() + "'";
}

// Every face mesh of an assimp scene in one TriangleMesh; polygons become fans. Throws MeshError
// for a face index past its mesh's vertices.
TriangleMesh MeshFromScene(const aiScene& scene, const std::filesystem::path& path) {
  TriangleMesh mesh;
  for (unsigned m = 0; m < scene.mNumMeshes; ++m) {
    const aiMesh* am = scene.mMeshes[m];
    if (!(am->mPrimitiveTypes & (aiPrimitiveType_TRIANGLE | aiPrimitiveType_POLYGON))) continue;
    const int offset = mesh.NumVertices();
    for (unsigned i = 0; i < am->mNumVertices; ++i) {
      const aiVector3D& v = am->mVertices[i];
      mesh.vertices.emplace_back(v.x, v.y, v.z);
    }
    for (unsigned f = 0; f < am->mNumFaces; ++f) {
      const aiFace& face = am->mFaces[f];
      for (unsigned k = 0; k < face.mNumIndices; ++k) {
        if (face.mIndices[k] >= am->mNumVertices) {
          throw MeshError("mesh file " + Quoted(path) + ": face " + std::to_string(f) +
                          " uses vertex " + std::to_string(face.mIndices[k]) + " of " +
                          std::to_string(am->mNumVertices));
        }
      }
      for (unsigned k = 2; k < face.mNumIndices; ++k) {
        mesh.triangles.emplace_back(offset + static_cast<int>(face.mIndices[0]),
                                    offset + static_cast<int>(face.mIndices[k - 1]),
                                    offset + static_cast<int>(face.mIndices[k]));
      }
    }
  }
  return mesh;
}

template <typename T>
void Append(std::string& out, const T& value) {
  out.append(reinterpret_cast<const char*>(&value), sizeof(value));
}

std::string MeshReply(const TriangleMesh& mesh) {
  std::string out(1, kMeshReply);
  Append(out, static_cast<std::uint64_t>(mesh.vertices.size()));
  for (const Eigen::Vector3d& v : mesh.vertices)
    out.append(reinterpret_cast<const char*>(v.data()), 3 * sizeof(double));
  Append(out, static_cast<std::uint64_t>(mesh.triangles.size()));
  for (const Eigen::Vector3i& t : mesh.triangles)
    out.append(reinterpret_cast<const char*>(t.data()), 3 * sizeof(int));
  return out;
}

// Reads `n` items of `size` bytes at `*at`, or throws when the reply is shorter.
const char* Take(const std::string& reply, std::size_t* at, std::uint64_t n, std::size_t size) {
  if (n > (reply.size() - *at) / size) throw MeshError("the mesh importer's reply is cut short");
  const char* p = reply.data() + *at;
  *at += n * size;
  return p;
}

TriangleMesh MeshFromReply(const std::string& reply) {
  TriangleMesh mesh;
  std::size_t at = 1;
  std::uint64_t n = 0;
  std::memcpy(&n, Take(reply, &at, 1, sizeof(n)), sizeof(n));
  const char* v = Take(reply, &at, n, 3 * sizeof(double));
  mesh.vertices.resize(n);
  for (std::uint64_t i = 0; i < n; ++i) {
    std::memcpy(mesh.vertices[i].data(), v + i * 3 * sizeof(double), 3 * sizeof(double));
  }
  std::memcpy(&n, Take(reply, &at, 1, sizeof(n)), sizeof(n));
  const char* t = Take(reply, &at, n, 3 * sizeof(int));
  mesh.triangles.resize(n);
  for (std::uint64_t i = 0; i < n; ++i) {
    std::memcpy(mesh.triangles[i].data(), t + i * 3 * sizeof(int), 3 * sizeof(int));
  }
  return mesh;
}

void WriteAll(int fd, const std::string& data) {
  std::size_t done = 0;
  while (done < data.size()) {
    const ssize_t n = ::write(fd, data.data() + done, data.size() - done);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) return;  // the parent gave up on us
    done += static_cast<std::size_t>(n);
  }
}

// The child's side: imports, replies, exits without running the parent's exit handlers.
[[noreturn]] void ImportAndReply(const std::filesystem::path& path, int fd) {
  // A crash must end this process with its signal, whatever handlers the parent installed.
  for (int sig : {SIGSEGV, SIGBUS, SIGFPE, SIGILL, SIGABRT}) std::signal(sig, SIG_DFL);
  std::string reply;
  try {
    Assimp::Importer importer;
    // Keep only faces: drop points and lines. Polygons are split here, as fans, not by assimp's
    // triangulation step, whose assertion aborts on some malformed faces.
    importer.SetPropertyInteger(AI_CONFIG_PP_SBP_REMOVE,
                                aiPrimitiveType_POINT | aiPrimitiveType_LINE);
    const aiScene* scene =
        importer.ReadFile(path.string(), aiProcess_PreTransformVertices | aiProcess_SortByPType);
    if (scene == nullptr) {
      reply = kErrorReply +
              ("cannot parse mesh file " + Quoted(path) + ": " + importer.GetErrorString());
    } else {
      reply = MeshReply(MeshFromScene(*scene, path));
    }
  } catch (const std::exception& e) {
    reply = kErrorReply + std::string(e.what());
  }
  WriteAll(fd, reply);
  ::_exit(0);
}

// Everything the child writes until it closes the pipe. Kills it and throws after `timeout_s`.
std::string ReadReply(int fd, pid_t child, double timeout_s, const std::filesystem::path& path) {
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::duration<double>(timeout_s);
  std::string reply;
  char buf[1 << 16];
  for (;;) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
        deadline - std::chrono::steady_clock::now());
    if (left.count() <= 0) {
      ::kill(child, SIGKILL);
      ::waitpid(child, nullptr, 0);
      throw MeshError("cannot parse mesh file " + Quoted(path) + ": the importer had not " +
                      "finished after " + FormatFixed(timeout_s, timeout_s < 1.0 ? 4 : 0) +
                      " s (a malformed file can make it loop)");
    }
    pollfd p{fd, POLLIN, 0};
    const int ready = ::poll(&p, 1, static_cast<int>(left.count()));
    if (ready <= 0) continue;  // EINTR or the deadline: checked above
    const ssize_t n = ::read(fd, buf, sizeof(buf));
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) return reply;
    reply.append(buf, static_cast<std::size_t>(n));
  }
}

}  // namespace

TriangleMesh ImportMeshFile(const std::filesystem::path& path, double timeout_s) {
  int fds[2];
  if (::pipe2(fds, O_CLOEXEC) != 0) {
    throw MeshError("cannot read mesh file " + Quoted(path) + ": pipe: " + std::strerror(errno));
  }
  const pid_t child = ::fork();
  if (child < 0) {
    const int err = errno;
    ::close(fds[0]);
    ::close(fds[1]);
    throw MeshError("cannot read mesh file " + Quoted(path) + ": fork: " + std::strerror(err));
  }
  if (child == 0) {
    ::close(fds[0]);
    ImportAndReply(path, fds[1]);
  }
  ::close(fds[1]);
  std::string reply;
  try {
    reply = ReadReply(fds[0], child, timeout_s, path);
  } catch (...) {
    ::close(fds[0]);
    throw;
  }
  ::close(fds[0]);
  int status = 0;
  while (::waitpid(child, &status, 0) < 0 && errno == EINTR) {
  }
  if (WIFSIGNALED(status)) {
    throw MeshError("cannot parse mesh file " + Quoted(path) + ": the importer (assimp) crashed " +
                    "on it (" + strsignal(WTERMSIG(status)) + "); the file is malformed");
  }
  if (!WIFEXITED(status) || WEXITSTATUS(status) != 0 || reply.empty()) {
    throw MeshError("cannot parse mesh file " + Quoted(path) +
                    ": the importer ended without an answer (exit status " +
                    std::to_string(WIFEXITED(status) ? WEXITSTATUS(status) : -1) + ")");
  }
  if (reply[0] == kErrorReply) throw MeshError(reply.substr(1));
  try {
    return MeshFromReply(reply);
  } catch (const MeshError& e) {
    throw MeshError("cannot parse mesh file " + Quoted(path) + ": " + e.what());
  }
}

}  // namespace gs360::geometry_internal
