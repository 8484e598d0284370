//! Rendering shared by the reference path tracer and (later) the LoD runtime: view files,
//! camera, lights, images and their comparison.

pub mod camera;
pub mod compare;
pub mod image;
pub mod label;
pub mod lights;
pub mod reference;
pub mod view;

pub use camera::Camera;
pub use image::Image;
pub use lights::{Environment, Lights, Sun};
pub use view::View;
