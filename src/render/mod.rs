//! What the reference renderer needs around it: view files, the reference path tracer itself,
//! image comparison and captions. Images, the camera and the image loop live in
//! [`crate::film`], the lights in [`crate::lights`]; the reference renderer depends on the
//! scene, the BVH and those alone, so that it stays an independent oracle for the LoD.

pub mod compare;
pub mod label;
pub mod reference;
mod view;

pub use view::*;
