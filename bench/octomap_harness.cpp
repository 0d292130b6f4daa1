// OctoMap side of bench.fusion_kernel: the same voxel stream through octomap::OcTree::updateNode.
//
// Input (little-endian): "VLMS", uint32 batches, uint32 voxels per batch, float64 resolution (m), then per
// batch the voxels' integer coordinates (uint16 i, j, k each) followed by one uint8 per voxel (1: hit, the
// label names the target; 0: miss). Voxel (i, j, k) is OctoMap key (i, j, k) + 2^15, the cell whose centre
// is at ((i + 1/2) res, ...), so every voxel of the grid is one leaf at full depth.
//
// Output: one JSON object on stdout: seconds per batch of updateNode(key, hit) for each voxel (the default,
// lazy_eval = false: inner nodes updated on the way, as a map server inserting a scan does), the same with
// lazy_eval = true plus one updateInnerOccupancy() per batch, and the tree's memoryUsage() and leaf count
// after the stream.
#include <octomap/OcTree.h>

#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <iostream>
#include <string>
#include <vector>

namespace {

struct Stream {
  uint32_t batches = 0, per_batch = 0;
  double resolution = 0.0;
  std::vector<uint16_t> ijk;   // batches * per_batch * 3
  std::vector<uint8_t> hits;   // batches * per_batch
};

bool read_stream(const char* path, Stream& s) {
  std::ifstream in(path, std::ios::binary);
  char magic[4];
  if (!in.read(magic, 4) || std::memcmp(magic, "VLMS", 4) != 0) return false;
  in.read(reinterpret_cast<char*>(&s.batches), 4);
  in.read(reinterpret_cast<char*>(&s.per_batch), 4);
  in.read(reinterpret_cast<char*>(&s.resolution), 8);
  const size_t n = size_t(s.batches) * s.per_batch;
  s.ijk.resize(n * 3);
  s.hits.resize(n);
  for (uint32_t b = 0; b < s.batches && in; ++b) {
    in.read(reinterpret_cast<char*>(&s.ijk[size_t(b) * s.per_batch * 3]), s.per_batch * 6);
    in.read(reinterpret_cast<char*>(&s.hits[size_t(b) * s.per_batch]), s.per_batch);
  }
  return bool(in);
}

// Seconds per batch; the tree is left as the stream made it.
std::vector<double> run(const Stream& s, octomap::OcTree& tree, bool lazy) {
  std::vector<double> seconds;
  const uint16_t offset = 1 << 15;
  for (uint32_t b = 0; b < s.batches; ++b) {
    const size_t first = size_t(b) * s.per_batch;
    const auto start = std::chrono::steady_clock::now();
    for (size_t v = first; v < first + s.per_batch; ++v) {
      const octomap::OcTreeKey key(s.ijk[3 * v] + offset, s.ijk[3 * v + 1] + offset, s.ijk[3 * v + 2] + offset);
      tree.updateNode(key, s.hits[v] != 0, lazy);
    }
    if (lazy) tree.updateInnerOccupancy();
    seconds.push_back(std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count());
  }
  return seconds;
}

void print_list(const char* name, const std::vector<double>& values) {
  std::printf("\"%s\": [", name);
  for (size_t i = 0; i < values.size(); ++i) std::printf(i ? ", %.9f" : "%.9f", values[i]);
  std::printf("]");
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 2) {
    std::cerr << "usage: " << argv[0] << " STREAM_FILE\n";
    return 2;
  }
  Stream s;
  if (!read_stream(argv[1], s)) {
    std::cerr << "cannot read the voxel stream " << argv[1] << "\n";
    return 1;
  }
  octomap::OcTree tree(s.resolution);
  const std::vector<double> eager = run(s, tree, false);
  octomap::OcTree lazy_tree(s.resolution);
  const std::vector<double> lazy = run(s, lazy_tree, true);
  std::printf("{\"voxels_per_batch\": %u, ", s.per_batch);
  print_list("seconds", eager);
  std::printf(", ");
  print_list("lazy_seconds", lazy);
  std::printf(", \"memory_bytes\": %zu, \"leaves\": %zu, \"nodes\": %zu, \"node_bytes\": %zu}\n",
              tree.memoryUsage(), tree.getNumLeafNodes(), tree.size(), sizeof(octomap::OcTreeNode));
  return 0;
}
