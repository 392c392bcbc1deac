// AdamW with decoupled weight decay, global gradient-norm clipping and the EMA of the weights,
// one launch per parameter tensor (compiled at run time by NVRTC, `fused.rs`). Every array is
// f32, contiguous, of `n` elements; `value`, `first`, `second` and `average` are updated in place.
//
// The clipping factor is computed here from the squared gradient norm on the device, so the host
// reads nothing before the update. A non-finite norm (a NaN or infinite loss) leaves every array
// as it was: the host reads the norm after launching and refuses the step.
//
// The arithmetic follows the tensor-operation path of `adamw.rs` and `ema.rs` term for term
// (a product by the reciprocal of sqrt(1 - beta2^t), then epsilon).
extern "C" __global__ void adamw_ema_f32(
    float* value,
    float* first,
    float* second,
    float* average,
    const float* gradient,
    const float* squared_norm,
    double clip,             // the global norm clip; infinity: no clipping
    float beta1,
    float beta2,
    float step_size,         // lr / (1 - beta1^t)
    float inverse_root_correction2,  // 1 / sqrt(1 - beta2^t)
    float epsilon,
    float keep,              // 1 - lr * weight_decay (1 for vectors and biases)
    float ema_decay,         // d of ema = d ema + (1 - d) value
    unsigned int n)
{
    float total = *squared_norm;
    // NaN fails every comparison; the sum of squares is never below 0.
    if (!(total <= 3.402823466e38f)) {
        return;
    }
    double norm = sqrt((double)total);
    float scale = norm > clip ? (float)(clip / (norm + 1e-6)) : 1.0f;
    for (unsigned int i = blockIdx.x * blockDim.x + threadIdx.x; i < n;
         i += blockDim.x * gridDim.x) {
        float g = gradient[i] * scale;
        float m = first[i] * beta1 + g * (1.0f - beta1);
        float v = second[i] * beta2 + (g * g) * (1.0f - beta2);
        first[i] = m;
        second[i] = v;
        float denominator = sqrtf(v) * inverse_root_correction2 + epsilon;
        float x = value[i] * keep - (m * step_size) / denominator;
        value[i] = x;
        average[i] = average[i] * ema_decay + x * (1.0f - ema_decay);
    }
}
