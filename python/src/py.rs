//! The PyO3 module `formation._formation`. Python's `formation` package
//! (python/formation/__init__.py) wraps it; users call that.

use std::path::PathBuf;

use numpy::{PyArray1, PyArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

use formation_scenario::generate::Spec;

use crate::keys::{graph_kind, Source};
use crate::memory::Columns;

fn value_error(e: String) -> PyErr {
    PyValueError::new_err(e)
}

/// A scenario: TOML text and `--set` assignments, checked as the command
/// line checks them.
#[pyclass(module = "formation._formation", name = "RawScenario")]
#[derive(Clone)]
pub struct RawScenario {
    source: Source,
}

#[pymethods]
impl RawScenario {
    /// A file, or a built-in scenario by name.
    #[staticmethod]
    #[pyo3(signature = (path, overrides = Vec::new()))]
    fn load(path: PathBuf, overrides: Vec<String>) -> PyResult<Self> {
        Source::load(&path, overrides).map(|source| Self { source }).map_err(value_error)
    }

    /// TOML text; `name` is the run name when the text gives none.
    #[staticmethod]
    #[pyo3(signature = (text, name = "scenario".to_string(), label = None))]
    fn from_toml(text: String, name: String, label: Option<String>) -> PyResult<Self> {
        let label = label.unwrap_or_else(|| format!("{name} (text)"));
        Source::from_text(text, label, name, Vec::new()).map(|source| Self { source }).map_err(value_error)
    }

    /// `formation generate`'s scenario.
    #[staticmethod]
    #[pyo3(signature = (followers, graph, chords, leader_links, radius, seed))]
    fn generate(
        followers: u32,
        graph: &str,
        chords: u32,
        leader_links: u32,
        radius: Option<f64>,
        seed: u64,
    ) -> PyResult<Self> {
        let spec = Spec {
            chords,
            leader_links,
            radius,
            seed,
            ..Spec::new(followers, graph_kind(graph).map_err(value_error)?)
        };
        Source::generate(&spec).map(|source| Self { source }).map_err(value_error)
    }

    /// An independent copy (the same text, assignments and file).
    fn copy(&self) -> Self {
        self.clone()
    }

    /// Applies one `KEY=VALUE` assignment as `--set` does.
    fn set(&mut self, assignment: &str) -> PyResult<()> {
        self.source.set(assignment).map_err(value_error)
    }

    /// The value at a dotted key, or None.
    fn get<'py>(&self, py: Python<'py>, key: &str) -> PyResult<Option<Bound<'py, PyAny>>> {
        match self.source.get(key).map_err(value_error)? {
            Some(v) => Ok(Some(to_python(py, &v)?)),
            None => Ok(None),
        }
    }

    /// Every key of the scenario as it runs, as nested dicts.
    fn to_dict<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_python(py, &toml::Value::Table(self.source.table().map_err(value_error)?))
    }

    fn to_toml(&self) -> PyResult<String> {
        self.source.to_toml().map_err(value_error)
    }

    #[getter]
    fn name(&self) -> String {
        self.source.scenario.name.clone()
    }
    #[getter]
    fn label(&self) -> String {
        self.source.label.clone()
    }
    #[getter]
    fn text(&self) -> String {
        self.source.text.clone()
    }
    #[getter]
    fn overrides(&self) -> Vec<String> {
        self.source.overrides.clone()
    }
    #[getter]
    fn follower_ids(&self) -> Vec<u32> {
        self.source.scenario.followers.iter().map(|f| f.id).collect()
    }
    #[getter]
    fn steps(&self) -> u64 {
        self.source.scenario.steps()
    }
    #[getter]
    fn dt(&self) -> f64 {
        self.source.scenario.dt_s
    }
    /// The estimator's stability warning (docs/model.md), where it applies.
    #[getter]
    fn warning(&self) -> Option<String> {
        self.source.scenario.estimator_stability_warning()
    }
}

/// Columns as a dict of 1-D float64 arrays; each Vec becomes its array's
/// buffer (no copy).
fn columns<'py>(py: Python<'py>, c: Columns) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    for (name, data) in c.names.into_iter().zip(c.data) {
        d.set_item(name, PyArray1::from_vec(py, data))?;
    }
    Ok(d)
}

/// A run as the package's `Run` takes it: followers {id: {column: array}},
/// leader {column: array}, summary (summary.json's text), network
/// (network.json's text or None), error (why it stopped early, or None).
fn run_dict<'py>(
    py: Python<'py>,
    followers: Vec<(u32, Columns)>,
    leader: Columns,
    summary: String,
    network: Option<String>,
    error: Option<String>,
) -> PyResult<Bound<'py, PyDict>> {
    let by_id = PyDict::new(py);
    for (id, c) in followers {
        by_id.set_item(id, columns(py, c)?)?;
    }
    let d = PyDict::new(py);
    d.set_item("followers", by_id)?;
    d.set_item("leader", columns(py, leader)?)?;
    d.set_item("summary", summary)?;
    d.set_item("network", network)?;
    d.set_item("error", error)?;
    Ok(d)
}

/// Runs a scenario in process, the GIL released while it runs; the run as
/// [`run_dict`] gives it. `every` None: the summary only.
#[pyfunction]
#[pyo3(signature = (scenario, threads = 1, every = Some(1)))]
fn sim<'py>(
    py: Python<'py>,
    scenario: &RawScenario,
    threads: usize,
    every: Option<u64>,
) -> PyResult<Bound<'py, PyDict>> {
    let s = scenario.source.scenario.clone();
    let run = py.detach(move || crate::memory::run(&s, threads, every)).map_err(value_error)?;
    run_dict(py, run.followers, run.leader, run.summary.to_json(), None, run.error)
}

/// Reads a run folder, as [`run_dict`] gives a run.
#[pyfunction]
fn read_run<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Bound<'py, PyDict>> {
    let run = py.detach(move || crate::folder::read(&path)).map_err(value_error)?;
    run_dict(py, run.followers, run.leader, run.summary, run.network, None)
}

/// The paper over `seeds` seeds, every case `formation paper` runs (the
/// tables' four only without `claims`), on
/// `threads` threads with the GIL released: a dict of `tables` (two dicts:
/// title, seeds, ids, values: float64 (seeds, followers, 4), paper: (4, 4))
/// and `claims` (a dict per claim, as `claims.csv` has it, with its
/// per-seed values).
#[pyfunction]
#[pyo3(signature = (scenario, seeds, threads, claims = true))]
fn paper<'py>(
    py: Python<'py>,
    scenario: &RawScenario,
    seeds: u64,
    threads: usize,
    claims: bool,
) -> PyResult<Bound<'py, PyDict>> {
    // A scenario made from text runs from a file of that text.
    let (path, _file) = match &scenario.source.path {
        Some(p) => (p.clone(), None),
        None => {
            let f = tempfile::Builder::new().suffix(".toml").tempfile().map_err(|e| value_error(e.to_string()))?;
            std::fs::write(f.path(), &scenario.source.text).map_err(|e| value_error(e.to_string()))?;
            (f.path().to_path_buf(), Some(f))
        }
    };
    let user = scenario.source.overrides.clone();
    let paper = py.detach(move || crate::paper::paper(&path, &user, seeds, threads, claims)).map_err(value_error)?;
    let tables = paper
        .tables
        .into_iter()
        .map(|t| {
            let d = PyDict::new(py);
            let (n, f) = (t.values.len(), t.ids.len());
            let flat: Vec<f64> = t.values.iter().flatten().flatten().copied().collect();
            d.set_item("title", t.title)?;
            d.set_item("seeds", t.seeds)?;
            d.set_item("ids", t.ids)?;
            d.set_item("values", PyArray1::from_vec(py, flat).reshape([n, f, 4])?)?;
            let paper: Vec<f64> = t.paper.iter().flatten().copied().collect();
            d.set_item("paper", PyArray1::from_vec(py, paper).reshape([4, 4])?)?;
            Ok(d)
        })
        .collect::<PyResult<Vec<_>>>()?;
    let claims = paper.claims.into_iter().map(|c| claim_dict(py, c)).collect::<PyResult<Vec<_>>>()?;
    let d = PyDict::new(py);
    d.set_item("tables", tables)?;
    d.set_item("claims", claims)?;
    Ok(d)
}

/// One checked claim: its words, what is measured and required, the
/// per-seed values, how many hold, and PASS, FAIL or N/A (with why).
fn claim_dict(py: Python<'_>, c: formation_report::tables::Check) -> PyResult<Bound<'_, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("result", c.result())?;
    d.set_item("measured", c.measured())?;
    d.set_item("required", c.condition.text())?;
    // The condition as numbers: (op, bound) or ("near", target, tolerance).
    use formation_report::tables::Cond;
    match c.condition {
        Cond::Lt(b) => d.set_item("condition", ("<", b))?,
        Cond::Le(b) => d.set_item("condition", ("<=", b))?,
        Cond::Gt(b) => d.set_item("condition", (">", b))?,
        Cond::Ge(b) => d.set_item("condition", (">=", b))?,
        Cond::Near { target, tol } => d.set_item("condition", ("near", target, tol))?,
    }
    d.set_item("claim", c.claim)?;
    d.set_item("quantity", c.quantity)?;
    d.set_item("unit", c.unit)?;
    d.set_item("cases", c.cases)?;
    d.set_item("holds", c.holds)?;
    d.set_item("missing", c.missing)?;
    d.set_item("values", PyArray1::from_vec(py, c.values))?;
    Ok(d)
}

/// A networked run re-computed from its hearing record (or the model's):
/// the dict of [`read_run`] plus problems (what could not be re-computed).
#[pyfunction]
#[pyo3(signature = (path, model = false))]
fn replay<'py>(py: Python<'py>, path: PathBuf, model: bool) -> PyResult<Bound<'py, PyDict>> {
    let (run, problems) = py.detach(move || crate::folder::replay(&path, model)).map_err(value_error)?;
    let d = run_dict(py, run.followers, run.leader, run.summary, run.network, None)?;
    d.set_item("problems", problems)?;
    Ok(d)
}

fn to_python<'py>(py: Python<'py>, v: &toml::Value) -> PyResult<Bound<'py, PyAny>> {
    Ok(match v {
        toml::Value::String(s) => s.into_pyobject(py)?.into_any(),
        toml::Value::Integer(i) => i.into_pyobject(py)?.into_any(),
        toml::Value::Float(f) => f.into_pyobject(py)?.into_any(),
        toml::Value::Boolean(b) => b.into_pyobject(py)?.to_owned().into_any(),
        toml::Value::Datetime(d) => d.to_string().into_pyobject(py)?.into_any(),
        toml::Value::Array(a) => {
            let items = a.iter().map(|x| to_python(py, x)).collect::<PyResult<Vec<_>>>()?;
            PyList::new(py, items)?.into_any()
        }
        toml::Value::Table(t) => {
            let d = PyDict::new(py);
            for (k, x) in t {
                d.set_item(k, to_python(py, x)?)?;
            }
            d.into_any()
        }
    })
}

/// The Rust half of the `formation` package.
#[pymodule]
fn _formation(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<RawScenario>()?;
    m.add_function(wrap_pyfunction!(sim, m)?)?;
    m.add_function(wrap_pyfunction!(read_run, m)?)?;
    m.add_function(wrap_pyfunction!(paper, m)?)?;
    m.add_function(wrap_pyfunction!(replay, m)?)?;
    m.add("MAX_VALUES", crate::memory::MAX_VALUES)?;
    Ok(())
}
