//! torch zip checkpoints (`torch.save` since PyTorch 1.6): [`read`] finds every tensor in the
//! pickle without running it; [`write`] writes f32 tensors in the release's
//! `{"model": state_dict, "meta_cfg": config}` layout for `torch.load`.

pub mod read;
pub mod write;

pub use read::{for_each_tensor, read_torch_zip, read_torch_zip_bytes, TorchEntry};
pub use write::write_torch_zip;
