//! # lifegom-estimate
//!
//! What a folder of plain photos does not say, estimated, so that it becomes the capture data
//! the rest of lifegom reads: the person in each photo (MediaPipe's BlazePose detector and
//! landmark model), its mask (the landmark model's segmentation or the selfie model), run on
//! Burn through `lifegom-tflite`.
//!
//! | module | concept |
//! |---|---|
//! | [`graphs`] | the three MediaPipe graphs: the pinned registry wheel they ship in, fetching, loading |
//! | [`crop`] | rotated crops of a photo onto a graph's square input (OpenCV's bilinear arithmetic), and back |
//! | [`detector`] | BlazePose's detector: SSD anchors, decoding, weighted non-maximum suppression |
//! | [`landmarks`] | BlazePose's landmark model on a detection's crop: 33 landmarks, heatmap refinement, the mask |
//! | [`selfie`] | the selfie segmentation model on the whole photo: a second person mask |
//! | [`person`] | the person in one photo, in one call: detection, crop, landmarks, mask; errors name the photo |
//! | [`overlay`] | the photo with the mask's edge and the skeleton drawn over it, for a person to check |

pub mod crop;
pub mod detector;
pub mod graphs;
pub mod landmarks;
pub mod overlay;
pub mod person;
pub mod selfie;
