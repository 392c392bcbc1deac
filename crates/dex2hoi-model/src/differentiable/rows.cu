// Layer norm, AdaLN's modulation and the attention's masked softmax on a GPU, forward and
// backward, one thread block per row: the CUDA side of the `LayerNorm`, `Modulate` and
// `MaskedSoftmax` operations (`differentiable.rs`, `modulate.rs`, `softmax.rs`), with the same
// formulas, a layer norm's statistics in two passes as on the CPU (the mean, then the mean of
// the centred squares). Compiled at run time by NVRTC (`rows_cuda.rs`).
//
// Layouts (all contiguous f32): tokens [rows, width]; for the modulation the rows are
// [sequences, frames] and each sequence's modulation row is [2 width], the shift then the scale.
// Blocks are a multiple of 32 threads, at most 1024.

// Negative infinity for the largest, 0 for the sum.
__device__ float identity(bool largest) {
    return largest ? __int_as_float(0xff800000u) : 0.0f;
}

__device__ float combine(float a, float b, bool largest) {
    return largest ? fmaxf(a, b) : a + b;
}

// The sum (or the largest) of one value per thread, returned to every thread of the block.
__device__ float block_reduce(float value, float* shared, bool largest) {
    for (int offset = 16; offset > 0; offset >>= 1) {
        value = combine(value, __shfl_down_sync(0xffffffffu, value, offset), largest);
    }
    unsigned int lane = threadIdx.x & 31u, warp = threadIdx.x >> 5;
    __syncthreads();  // the previous sum's readers are done with `shared`
    if (lane == 0) shared[warp] = value;
    __syncthreads();
    if (warp == 0) {
        value = threadIdx.x < (blockDim.x >> 5) ? shared[threadIdx.x] : identity(largest);
        for (int offset = 16; offset > 0; offset >>= 1) {
            value = combine(value, __shfl_down_sync(0xffffffffu, value, offset), largest);
        }
        if (lane == 0) shared[32] = value;
    }
    __syncthreads();
    return shared[32];
}

__device__ float block_sum(float value, float* shared) {
    return block_reduce(value, shared, false);
}

// The row's mean and `1 / sqrt(variance + eps)`.
__device__ void statistics(const float* x, unsigned int width, float eps, float* shared,
                           float* mean, float* inverse) {
    float sum = 0.0f;
    for (unsigned int i = threadIdx.x; i < width; i += blockDim.x) sum += x[i];
    float mu = block_sum(sum, shared) / (float)width;
    float squares = 0.0f;
    for (unsigned int i = threadIdx.x; i < width; i += blockDim.x) {
        float centred = x[i] - mu;
        squares = fmaf(centred, centred, squares);
    }
    float variance = block_sum(squares, shared) / (float)width;
    *mean = mu;
    *inverse = 1.0f / sqrtf(variance + eps);
}

extern "C" __global__ void layer_norm_forward_f32(const float* x, unsigned int width, float eps,
                                                  float* out) {
    __shared__ float shared[33];
    size_t row = (size_t)blockIdx.x * width;
    float mu, inverse;
    statistics(x + row, width, eps, shared, &mu, &inverse);
    for (unsigned int i = threadIdx.x; i < width; i += blockDim.x) {
        out[row + i] = (x[row + i] - mu) * inverse;
    }
}

// dx = (g - mean(g) - y mean(g y)) inverse, with y the normalised row.
extern "C" __global__ void layer_norm_backward_f32(const float* x, const float* g,
                                                   unsigned int width, float eps, float* dx) {
    __shared__ float shared[33];
    size_t row = (size_t)blockIdx.x * width;
    float mu, inverse;
    statistics(x + row, width, eps, shared, &mu, &inverse);
    float g_sum = 0.0f, gy_sum = 0.0f;
    for (unsigned int i = threadIdx.x; i < width; i += blockDim.x) {
        float y = (x[row + i] - mu) * inverse;
        g_sum += g[row + i];
        gy_sum = fmaf(g[row + i], y, gy_sum);
    }
    float g_mean = block_sum(g_sum, shared) / (float)width;
    float gy_mean = block_sum(gy_sum, shared) / (float)width;
    for (unsigned int i = threadIdx.x; i < width; i += blockDim.x) {
        float y = (x[row + i] - mu) * inverse;
        dx[row + i] = (g[row + i] - g_mean - y * gy_mean) * inverse;
    }
}

// out = norm(x) (1 + scale) + shift, with the shift and scale of the row's sequence.
extern "C" __global__ void modulate_forward_f32(const float* x, const float* modulation,
                                                unsigned int frames, unsigned int width,
                                                float eps, float* out) {
    __shared__ float shared[33];
    size_t row = (size_t)blockIdx.x * width;
    const float* shift = modulation + (size_t)(blockIdx.x / frames) * 2 * width;
    const float* scale = shift + width;
    float mu, inverse;
    statistics(x + row, width, eps, shared, &mu, &inverse);
    for (unsigned int i = threadIdx.x; i < width; i += blockDim.x) {
        float y = (x[row + i] - mu) * inverse;
        out[row + i] = fmaf(y, 1.0f + scale[i], shift[i]);
    }
}

// The tokens' gradient, row by row: with u = g (1 + scale), dx = (u - mean(u) - y mean(u y))
// inverse. Each row's mean and inverse go to `stats` [rows, 2] for the columns' pass.
extern "C" __global__ void modulate_backward_rows_f32(const float* x, const float* modulation,
                                                      const float* g, unsigned int frames,
                                                      unsigned int width, float eps, float* dx,
                                                      float* stats) {
    __shared__ float shared[33];
    size_t row = (size_t)blockIdx.x * width;
    const float* scale = modulation + (size_t)(blockIdx.x / frames) * 2 * width + width;
    float mu, inverse;
    statistics(x + row, width, eps, shared, &mu, &inverse);
    float u_sum = 0.0f, uy_sum = 0.0f;
    for (unsigned int i = threadIdx.x; i < width; i += blockDim.x) {
        float y = (x[row + i] - mu) * inverse;
        float u = g[row + i] * (1.0f + scale[i]);
        u_sum += u;
        uy_sum = fmaf(u, y, uy_sum);
    }
    float u_mean = block_sum(u_sum, shared) / (float)width;
    float uy_mean = block_sum(uy_sum, shared) / (float)width;
    for (unsigned int i = threadIdx.x; i < width; i += blockDim.x) {
        float y = (x[row + i] - mu) * inverse;
        float u = g[row + i] * (1.0f + scale[i]);
        dx[row + i] = (u - u_mean - y * uy_mean) * inverse;
    }
    if (threadIdx.x == 0) {
        stats[2 * (size_t)blockIdx.x] = mu;
        stats[2 * (size_t)blockIdx.x + 1] = inverse;
    }
}

// The modulation's gradient, one thread per (sequence, feature): d shift = sum_t g,
// d scale = sum_t g y over the sequence's frames, into [sequences, 2 width].
extern "C" __global__ void modulate_backward_columns_f32(const float* x, const float* g,
                                                         const float* stats,
                                                         unsigned int sequences,
                                                         unsigned int frames, unsigned int width,
                                                         float* d_modulation) {
    size_t index = (size_t)blockIdx.x * blockDim.x + threadIdx.x;
    if (index >= (size_t)sequences * width) return;
    size_t sequence = index / width, feature = index % width;
    float d_shift = 0.0f, d_scale = 0.0f;
    for (unsigned int t = 0; t < frames; t++) {
        size_t row = sequence * frames + t;
        float y = (x[row * width + feature] - stats[2 * row]) * stats[2 * row + 1];
        float gradient = g[row * width + feature];
        d_shift += gradient;
        d_scale = fmaf(gradient, y, d_scale);
    }
    d_modulation[sequence * 2 * width + feature] = d_shift;
    d_modulation[sequence * 2 * width + width + feature] = d_scale;
}

// probabilities = softmax(scores + (mask - 1) 1e9) per row, with the mask row [width] of the
// row's sequence (`rows_per_sequence` consecutive rows each).
extern "C" __global__ void masked_softmax_forward_f32(const float* scores, const float* mask,
                                                      unsigned int rows_per_sequence,
                                                      unsigned int width, float* out) {
    __shared__ float shared[33];
    size_t row = (size_t)blockIdx.x * width;
    const float* keep = mask + (size_t)(blockIdx.x / rows_per_sequence) * width;
    float largest = identity(true);
    for (unsigned int i = threadIdx.x; i < width; i += blockDim.x) {
        float biased = scores[row + i] + (keep[i] - 1.0f) * 1e9f;
        out[row + i] = biased;
        largest = fmaxf(largest, biased);
    }
    largest = block_reduce(largest, shared, true);
    float sum = 0.0f;
    for (unsigned int i = threadIdx.x; i < width; i += blockDim.x) {
        float e = expf(out[row + i] - largest);
        out[row + i] = e;
        sum += e;
    }
    sum = block_sum(sum, shared);
    for (unsigned int i = threadIdx.x; i < width; i += blockDim.x) out[row + i] /= sum;
}

// dx = y (g - sum(g y)) per row, from the softmax's output y.
extern "C" __global__ void softmax_backward_f32(const float* y, const float* g, unsigned int width,
                                                float* dx) {
    __shared__ float shared[33];
    size_t row = (size_t)blockIdx.x * width;
    float gy = 0.0f;
    for (unsigned int i = threadIdx.x; i < width; i += blockDim.x) {
        gy = fmaf(g[row + i], y[row + i], gy);
    }
    gy = block_sum(gy, shared);
    for (unsigned int i = threadIdx.x; i < width; i += blockDim.x) {
        dx[row + i] = y[row + i] * (g[row + i] - gy);
    }
}
