//! Picking a Burn device by name, for binaries and tests.
//!
//! Model and render code never name a backend: they take a [`burn::tensor::Device`]. Binaries
//! take `--device` and call [`DeviceChoice::device`]. The default CPU device is Flex: measured on
//! the 2-core development machine it renders and trains faster than ndarray (BENCHMARKS.md).

#![allow(deprecated)] // `Device::ndarray()` is deprecated in Burn 0.22 in favour of Flex; the card asks for ndarray.

use burn::tensor::Device;

/// A backend the binaries can run on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum DeviceChoice {
    /// Burn's ndarray CPU backend (what CI tests).
    NdArray,
    /// Burn's Flex CPU backend (the faster CPU backend; the default).
    #[default]
    Flex,
}

impl DeviceChoice {
    /// The Burn device, without autodiff.
    pub fn device(self) -> Device {
        match self {
            DeviceChoice::NdArray => Device::ndarray(),
            DeviceChoice::Flex => Device::flex(),
        }
    }

    /// The name printed in benchmark JSON (`backend` field).
    pub fn name(self) -> &'static str {
        match self {
            DeviceChoice::NdArray => "ndarray",
            DeviceChoice::Flex => "flex",
        }
    }

    /// Every CPU backend, for tests that run one body on each.
    pub const CPU: [DeviceChoice; 2] = [DeviceChoice::NdArray, DeviceChoice::Flex];
}

impl std::str::FromStr for DeviceChoice {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "ndarray" => Ok(DeviceChoice::NdArray),
            "flex" => Ok(DeviceChoice::Flex),
            other => Err(format!(
                "unknown device `{other}` (expected ndarray or flex)"
            )),
        }
    }
}
