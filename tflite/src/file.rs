//! Reading a `.tflite` file into a [`Program`]: its first subgraph's tensors (shapes, names,
//! constants made f32 and dense) and its operators decoded and shape-checked, on the host.
//! Nothing here touches a device.

use planus::ReadAsRoot;

use crate::error::{Result, TfliteError};
use crate::op::{self, InputView, Op};
use crate::schema::tflite as fb;
use crate::sparse::{self, Dimension};

/// The most elements one tensor may have (a constant or an activation): 2^26, 256 MiB of f32.
/// The MediaPipe graphs' largest has 2^21.
const MAX_ELEMENTS: usize = 1 << 26;

/// A tensor's constant value, in the file's own element order.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Constant {
    Float(Vec<f32>),
    Int(Vec<i32>),
}

/// A tensor as declared.
#[derive(Debug, Clone)]
pub(crate) struct TensorDecl {
    pub name: String,
    pub shape: Vec<usize>,
    pub constant: Option<Constant>,
}

/// One operator to run.
#[derive(Debug, Clone)]
pub(crate) struct Node {
    pub op: Op,
    pub inputs: Vec<usize>,
    pub output: usize,
}

/// A graph read from a file: what [`crate::Graph`] uploads and runs.
#[derive(Debug, Clone)]
pub(crate) struct Program {
    pub name: String,
    pub tensors: Vec<TensorDecl>,
    pub inputs: Vec<usize>,
    pub outputs: Vec<usize>,
    pub nodes: Vec<Node>,
}

/// Reads the model in `bytes`, naming it `name` in errors.
pub(crate) fn read(name: &str, bytes: &[u8]) -> Result<Program> {
    let format = |reason: String| TfliteError::Format {
        graph: name.to_string(),
        reason,
    };
    let pl = |what: &'static str| move |e: planus::Error| format(format!("{what}: {e}"));
    if bytes.len() < 8 || &bytes[4..8] != b"TFL3" {
        return Err(format("no TFL3 file identifier".into()));
    }
    let model = fb::ModelRef::read_as_root(bytes).map_err(pl("model"))?;
    let subgraphs = model
        .subgraphs()
        .map_err(pl("subgraphs"))?
        .ok_or_else(|| format("no subgraphs".into()))?;
    if subgraphs.len() != 1 {
        return Err(format(format!(
            "{} subgraphs; graphs with control flow are not run here",
            subgraphs.len()
        )));
    }
    let graph = subgraphs
        .get(0)
        .ok_or_else(|| format("no subgraphs".into()))?
        .map_err(pl("subgraph 0"))?;
    let buffers = model.buffers().map_err(pl("buffers"))?;
    let codes = model.operator_codes().map_err(pl("operator codes"))?;

    let fb_tensors = graph
        .tensors()
        .map_err(pl("tensors"))?
        .ok_or_else(|| format("no tensors".into()))?;
    let mut tensors = Vec::with_capacity(fb_tensors.len());
    for (index, tensor) in fb_tensors.iter().enumerate() {
        let tensor = tensor.map_err(pl("tensor"))?;
        tensors.push(read_tensor(name, index, &tensor, bytes, buffers)?);
    }
    let count = tensors.len();
    let index_list = |list: Option<planus::Vector<'_, i32>>, what: &str| -> Result<Vec<usize>> {
        list.map_or(Ok(Vec::new()), |l| {
            l.iter()
                .map(|i| {
                    usize::try_from(i)
                        .ok()
                        .filter(|&i| i < count)
                        .ok_or_else(|| format(format!("{what} names tensor {i}, of {count}")))
                })
                .collect()
        })
    };
    let inputs = index_list(graph.inputs().map_err(pl("inputs"))?, "the graph's inputs")?;
    let outputs = index_list(
        graph.outputs().map_err(pl("outputs"))?,
        "the graph's outputs",
    )?;
    if inputs.is_empty() || outputs.is_empty() {
        return Err(format("the graph has no inputs or no outputs".into()));
    }

    let operators = graph.operators().map_err(pl("operators"))?;
    let mut nodes = Vec::new();
    let mut produced: Vec<bool> = tensors.iter().map(|t| t.constant.is_some()).collect();
    for &i in &inputs {
        produced[i] = true;
    }
    for (index, operator) in operators.into_iter().flatten().enumerate() {
        let operator = operator.map_err(pl("operator"))?;
        let opcode = operator.opcode_index().map_err(pl("operator"))? as usize;
        let code = codes
            .and_then(|c| c.get(opcode))
            .and_then(|c| c.ok())
            .ok_or_else(|| format(format!("operator {index} names operator code {opcode}")))?;
        // Files before schema 3a keep the number in the deprecated byte; after, in the int.
        let builtin = code
            .builtin_code()
            .map_err(pl("operator code"))?
            .max(i32::from(
                code.deprecated_builtin_code()
                    .map_err(pl("operator code"))?,
            ));
        let custom = code.custom_code().map_err(pl("operator code"))?;
        let op_name = match custom {
            Some(c) if builtin == op::code::CUSTOM => c.to_string(),
            _ => op::builtin_name(builtin),
        };
        let op_err = |reason: String| TfliteError::Operator {
            graph: name.to_string(),
            index,
            op: op_name.clone(),
            reason,
        };
        let ins = index_list(
            operator.inputs().map_err(pl("operator inputs"))?,
            "an operator",
        )
        .map_err(|e| op_err(e.to_string()))?;
        let outs = index_list(
            operator.outputs().map_err(pl("operator outputs"))?,
            "an operator",
        )
        .map_err(|e| op_err(e.to_string()))?;
        let [output] = outs[..] else {
            return Err(op_err(format!("{} outputs, expected 1", outs.len())));
        };
        if let Some(&missing) = ins.iter().find(|&&i| !produced[i]) {
            return Err(op_err(format!(
                "input tensor {missing} `{}` is neither a constant, a graph input nor an \
                 earlier operator's output",
                tensors[missing].name
            )));
        }
        if produced[output] {
            return Err(op_err(format!(
                "its output tensor {output} is already defined"
            )));
        }
        produced[output] = true;

        if builtin == op::code::DEQUANTIZE || builtin == op::code::DENSIFY {
            // Both only ever turn a stored constant into its f32 dense value, which reading
            // the constant already did.
            let [input] = ins[..] else {
                return Err(op_err(format!("{} inputs, expected 1", ins.len())));
            };
            let Some(Constant::Float(values)) = tensors[input].constant.clone() else {
                return Err(op_err("its input is not a float constant".into()));
            };
            if tensors[input].shape != tensors[output].shape {
                return Err(op_err(format!(
                    "input {:?} and output {:?} differ in shape",
                    tensors[input].shape, tensors[output].shape
                )));
            }
            tensors[output].constant = Some(Constant::Float(values));
            continue;
        }

        let views: Vec<InputView<'_>> = ins
            .iter()
            .map(|&i| InputView {
                shape: &tensors[i].shape,
                ints: match &tensors[i].constant {
                    Some(Constant::Int(v)) => Some(v),
                    _ => None,
                },
                is_constant: tensors[i].constant.is_some(),
            })
            .collect();
        let (op, shape) = op::decode(builtin, custom, &operator, &views).map_err(op_err)?;
        let declared = &tensors[output].shape;
        let fits = if op == Op::Reshape {
            declared.iter().product::<usize>() == tensors[ins[0]].shape.iter().product::<usize>()
                && declared.len() <= 4
        } else {
            &shape == declared
        };
        if !fits {
            return Err(op_err(format!(
                "it makes {:?} from {:?}, the file declares {declared:?}",
                if op == Op::Reshape {
                    &tensors[ins[0]].shape
                } else {
                    &shape
                },
                ins.iter().map(|&i| &tensors[i].shape).collect::<Vec<_>>()
            )));
        }
        nodes.push(Node {
            op,
            inputs: ins,
            output,
        });
    }
    for &o in &outputs {
        if !produced[o] {
            return Err(format(format!(
                "graph output {o} `{}` is never computed",
                tensors[o].name
            )));
        }
    }
    for &i in inputs.iter().chain(&outputs) {
        let tensor_err = |reason: &str| TfliteError::Tensor {
            graph: name.to_string(),
            index: i,
            name: tensors[i].name.clone(),
            reason: reason.to_string(),
        };
        if inputs.contains(&i) && tensors[i].constant.is_some() {
            return Err(tensor_err("a graph input that is a constant"));
        }
        if matches!(tensors[i].constant, Some(Constant::Int(_))) {
            return Err(tensor_err("an int32 constant as a graph output"));
        }
        if tensors[i].shape.is_empty() || tensors[i].shape.len() > 4 {
            return Err(TfliteError::Tensor {
                graph: name.to_string(),
                index: i,
                name: tensors[i].name.clone(),
                reason: format!("a graph input or output of shape {:?}", tensors[i].shape),
            });
        }
    }
    Ok(Program {
        name: name.to_string(),
        tensors,
        inputs,
        outputs,
        nodes,
    })
}

fn read_tensor(
    graph: &str,
    index: usize,
    tensor: &fb::TensorRef<'_>,
    file: &[u8],
    buffers: Option<planus::Vector<'_, planus::Result<fb::BufferRef<'_>>>>,
) -> Result<TensorDecl> {
    let tensor_name = tensor.name().ok().flatten().unwrap_or("").to_string();
    let err = |reason: String| TfliteError::Tensor {
        graph: graph.to_string(),
        index,
        name: tensor_name.clone(),
        reason,
    };
    let pl = |e: planus::Error| err(e.to_string());
    let shape: Vec<usize> = match tensor.shape().map_err(pl)? {
        Some(s) => s
            .iter()
            .map(|d| {
                usize::try_from(d)
                    .ok()
                    .filter(|&d| (1..=MAX_ELEMENTS).contains(&d))
            })
            .collect::<Option<_>>()
            .ok_or_else(|| err("a dimension that is not a positive size".into()))?,
        None => Vec::new(),
    };
    if shape.len() > 6 {
        return Err(err(format!("rank {}", shape.len())));
    }
    let elements = shape
        .iter()
        .try_fold(1usize, |n, &d| {
            n.checked_mul(d).filter(|&n| n <= MAX_ELEMENTS)
        })
        .ok_or_else(|| {
            err(format!(
                "shape {shape:?}: more than {MAX_ELEMENTS} elements"
            ))
        })?;
    let buffer = tensor.buffer().map_err(pl)? as usize;
    // Buffer 0 is the empty sentinel: not a constant.
    let data = if buffer == 0 {
        None
    } else {
        let b = buffers
            .and_then(|b| b.get(buffer))
            .and_then(|b| b.ok())
            .ok_or_else(|| err(format!("names buffer {buffer}, which the file lacks")))?;
        let inline = b.data().map_err(pl)?;
        let (offset, size) = (b.offset().map_err(pl)?, b.size().map_err(pl)?);
        match inline {
            Some(d) if !d.is_empty() => Some(d),
            _ if offset > 1 => {
                let range = usize::try_from(offset)
                    .ok()
                    .zip(usize::try_from(size).ok())
                    .and_then(|(o, s)| Some(o..o.checked_add(s)?))
                    .filter(|r| r.end <= file.len())
                    .ok_or_else(|| {
                        err(format!(
                            "buffer {buffer} at {offset}+{size} past the file's end"
                        ))
                    })?;
                Some(&file[range])
            }
            _ => None,
        }
    };
    let Some(data) = data else {
        return Ok(TensorDecl {
            name: tensor_name,
            shape,
            constant: None,
        });
    };
    let ty = tensor.type_().map_err(pl)?;
    let stored = match tensor.sparsity().map_err(pl)? {
        Some(_) => None,
        None => Some(elements),
    };
    let width = match ty {
        fb::TensorType::Float32 | fb::TensorType::Int32 => 4,
        fb::TensorType::Float16 => 2,
        other => return Err(err(format!("constant of type {other:?} is not read"))),
    };
    if data.len() % width != 0 || stored.is_some_and(|n| n * width != data.len()) {
        return Err(err(format!(
            "{} bytes of {ty:?} data for shape {shape:?}",
            data.len()
        )));
    }
    let constant = match ty {
        fb::TensorType::Int32 => Constant::Int(
            data.chunks_exact(4)
                .map(|c| i32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect(),
        ),
        fb::TensorType::Float16 => Constant::Float(
            data.chunks_exact(2)
                .map(|c| half::f16::from_le_bytes([c[0], c[1]]).to_f32())
                .collect(),
        ),
        _ => Constant::Float(
            data.chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect(),
        ),
    };
    let constant = match (tensor.sparsity().map_err(pl)?, constant) {
        (None, c) => c,
        (Some(sp), Constant::Float(values)) => {
            Constant::Float(dense(&shape, &sp, &values).map_err(|r| err(format!("sparse: {r}")))?)
        }
        (Some(_), Constant::Int(_)) => return Err(err("a sparse int32 constant".into())),
    };
    Ok(TensorDecl {
        name: tensor_name,
        shape,
        constant: Some(constant),
    })
}

/// The dense values of a sparse constant.
fn dense(
    shape: &[usize],
    sp: &fb::SparsityParametersRef<'_>,
    values: &[f32],
) -> std::result::Result<Vec<f32>, String> {
    let s = |e: planus::Error| e.to_string();
    if sp.block_map().map_err(s)?.is_some_and(|b| !b.is_empty()) {
        return Err("block-sparse constants are not read".into());
    }
    let order: Vec<usize> = sp
        .traversal_order()
        .map_err(s)?
        .ok_or("no traversal order")?
        .iter()
        .map(|d| usize::try_from(d).map_err(|_| format!("traversal entry {d}")))
        .collect::<std::result::Result<_, _>>()?;
    let mut dims = Vec::new();
    let metadata = sp
        .dim_metadata()
        .map_err(s)?
        .ok_or("no dimension records")?;
    for meta in metadata {
        let meta = meta.map_err(s)?;
        dims.push(match meta.format().map_err(s)? {
            fb::DimensionType::Dense => Dimension::Dense {
                size: usize::try_from(meta.dense_size().map_err(s)?)
                    .map_err(|_| "a negative dense size".to_string())?,
            },
            fb::DimensionType::SparseCsr => Dimension::Csr {
                segments: index_vector(meta.array_segments().map_err(s)?)?,
                indices: index_vector(meta.array_indices().map_err(s)?)?,
            },
        });
    }
    sparse::densify(shape, &order, &dims, values)
}

fn index_vector(
    v: Option<fb::SparseIndexVectorRef<'_>>,
) -> std::result::Result<Vec<usize>, String> {
    let s = |e: planus::Error| e.to_string();
    let v = v.ok_or("CSR dimension without its segments or indices")?;
    Ok(match v {
        fb::SparseIndexVectorRef::Int32Vector(v) => v
            .values()
            .map_err(s)?
            .map(|v| {
                v.iter()
                    .map(|i| usize::try_from(i).map_err(|_| format!("index {i}")))
                    .collect::<std::result::Result<Vec<_>, _>>()
            })
            .transpose()?
            .unwrap_or_default(),
        fb::SparseIndexVectorRef::Uint16Vector(v) => v
            .values()
            .map_err(s)?
            .map(|v| v.iter().map(usize::from).collect())
            .unwrap_or_default(),
        fb::SparseIndexVectorRef::Uint8Vector(v) => v
            .values()
            .map_err(s)?
            .map(|v| v.iter().map(|&i| usize::from(i)).collect())
            .unwrap_or_default(),
    })
}
