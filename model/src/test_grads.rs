//! Test helper: every parameter gradient of a module, by path, to compare devices.

use burn::module::{Module, ModuleVisitor, Param};
use burn::tensor::{Gradients, Tensor};
use lifegom_render::testing::read;

/// Every parameter of `module` that has a gradient in `grads`, as `(path, values)` in visiting
/// order.
pub(crate) fn parameter_grads<M: Module>(module: &M, grads: &Gradients) -> Vec<(String, Vec<f32>)> {
    let mut visitor = GradValues {
        grads,
        path: Vec::new(),
        out: Vec::new(),
    };
    module.visit(&mut visitor);
    visitor.out
}

struct GradValues<'a> {
    grads: &'a Gradients,
    path: Vec<String>,
    out: Vec<(String, Vec<f32>)>,
}

impl ModuleVisitor for GradValues<'_> {
    fn enter_module(&mut self, name: &str, _: &str) {
        self.path.push(name.to_string());
    }
    fn exit_module(&mut self, _: &str, _: &str) {
        self.path.pop();
    }
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        if let Some(g) = param.val().grad(self.grads) {
            self.out.push((self.path.join("."), read(g)));
        }
    }
}
