// One record through the online pipeline's AOTInductor package, from C++ (no Python, no phm_torch).
//
//   ./phm_aoti online.aoti.pt2 record.f32 [model|samples]
//
// record.f32: one record as raw little-endian float32 values, the current [A] of a full record (n_full values,
// program "model", the default) or of the selected samples (n_points values, program "samples"); NaN = missing.
// The offset input (the bench baseline, subtracted first) is zeros here. Prints one line per output of
// OnlineStep, in the package's order (k_hat k_lower k_upper score p_faulty rul ood residual noise consistency
// reasons): the output index followed by its values, printed as doubles with 17 significant digits.
#include <torch/csrc/inductor/aoti_package/model_package_loader.h>
#include <torch/torch.h>

#include <cstdio>
#include <fstream>
#include <iostream>
#include <iterator>
#include <string>
#include <vector>

int main(int argc, char** argv) {
  if (argc < 3 || argc > 4) {
    std::cerr << "usage: " << argv[0] << " PACKAGE.aoti.pt2 RECORD.f32 [model|samples]\n";
    return 2;
  }
  const std::string model_name = argc == 4 ? argv[3] : "model";
  std::ifstream in(argv[2], std::ios::binary);
  if (!in) {
    std::cerr << "record: cannot read " << argv[2] << "\n";
    return 2;
  }
  std::vector<char> bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  if (bytes.empty() || bytes.size() % sizeof(float) != 0) {
    std::cerr << "record: " << argv[2] << " holds " << bytes.size() << " bytes, not float32 values\n";
    return 2;
  }
  const int64_t n = static_cast<int64_t>(bytes.size() / sizeof(float));
  // (1, n) record and (n,) zero offset, float32 as the pipeline was exported (clone: the tensor owns its data)
  at::Tensor x = torch::from_blob(bytes.data(), {1, n}, torch::kFloat32).clone();
  at::Tensor offset = torch::zeros({n}, torch::kFloat32);

  c10::InferenceMode guard;
  torch::inductor::AOTIModelPackageLoader loader(argv[1], model_name, /*run_single_threaded=*/true);
  std::vector<at::Tensor> outputs = loader.run({x, offset});
  for (size_t i = 0; i < outputs.size(); ++i) {
    at::Tensor values = outputs[i].to(torch::kFloat64).contiguous().flatten();
    std::printf("%zu", i);
    const double* data = values.data_ptr<double>();
    for (int64_t j = 0; j < values.numel(); ++j) std::printf(" %.17g", data[j]);
    std::printf("\n");
  }
  return 0;
}
