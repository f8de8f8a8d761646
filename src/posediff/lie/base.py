"""The ``LieGroup`` base class: a stateless, tensor-first strategy object.

Conventions (written once here and in ``docs/conventions.md``):

* **Elements are plain tensors in matrix form**: SO3 ``(*b, 3, 3)``, R3SO3 and SE3 ``(*b, 4, 4)``
  (``[[R, t], [0, 1]]``), SE2 ``(*b, 3, 3)``. No tensor subclasses, no wrappers.
* **Tangent vectors** are ``(*b, dim)`` and ordered ``[ρ, φ]``: translation first, then rotation,
  as the paper's τ = (ρ, φ) (Sec. 3.1). ``rotation_slice`` says where the rotation part is.
* **Right perturbation**: ``Y = X · Exp(z)`` (paper Eq. 3); ``rplus(X, z) = X · Exp(z)`` and
  ``rminus(X, Y) = Log(X⁻¹ Y)``. Jacobians follow: ``Exp(z + δ) ≈ Exp(z) · Exp(J_r(z) δ)`` and
  ``Exp(z + δ) ≈ Exp(J_l(z) δ) · Exp(z)``.
* ``log`` is principal: the rotation angle of its result lies in [0, π].
* Every operation broadcasts over leading batch dimensions, keeps dtype and device, never writes
  into its inputs, and is differentiable (finite gradients at θ = 0 and θ = π).

Adding a group: subclass with a registry name and implement the ``_kernels`` (classmethods on
tensors whose shapes were already checked)::

    class Sim3(LieGroup, name="sim3"):
        dim = 7
        matrix_dim = 4
        rotation_slice = slice(3, 6)
        @classmethod
        def _exp(cls, xi): ...

``posediff.testing.lie_group_contract(Sim3())`` then checks it like the built-in groups, and the
test suite picks it up from the registry.
"""

import functools
from collections.abc import Callable, Sequence
from typing import Any, ClassVar

import torch
from torch import Tensor

from .._registry import Registered

BatchShape = Sequence[int] | torch.Size | int


class LieGroup(Registered, family=True):
    """A matrix Lie group with batched exp/log/compose/inverse/act and Jacobians in torch.

    Args:
        compiled: run the kernels through ``torch.compile`` (fused, much faster on large batches;
            the first call of each operation compiles for a few seconds). Under autograd the
            forward is the compiled kernel and the backward a compiled vector-Jacobian product of
            the same kernel (``torch.func.vjp``, compiled once per operation); a second derivative
            (``create_graph=True``) re-runs the eager kernel, so higher orders stay exact. Off by
            default.
    """

    family_label: ClassVar[str] = "Lie group"
    #: registry name (set by ``class X(LieGroup, name="x")``)
    name: ClassVar[str]
    #: tangent dimension
    dim: ClassVar[int]
    #: elements are ``(*b, matrix_dim, matrix_dim)``
    matrix_dim: ClassVar[int]
    #: where the rotation components sit in a tangent vector (the rest is translation)
    rotation_slice: ClassVar[slice]
    #: dimension of the points that ``act`` transforms
    point_dim: ClassVar[int] = 3

    def __init__(self, *, compiled: bool = False) -> None:
        self.compiled = bool(compiled)

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "name" in kwargs and kwargs["name"] is not None:
            missing = [a for a in ("dim", "matrix_dim", "rotation_slice") if not hasattr(cls, a)]
            if missing:
                raise TypeError(f"Lie group {cls.__qualname__} must define {', '.join(missing)}")

    def __repr__(self) -> str:
        return f"{type(self).__name__}(compiled=True)" if self.compiled else f"{type(self).__name__}()"

    def __eq__(self, other: object) -> bool:
        return type(other) is type(self) and other.compiled == self.compiled  # type: ignore[attr-defined]

    def __hash__(self) -> int:
        return hash((type(self), self.compiled))

    # ------------------------------------------------------------------ public API
    def exp(self, xi: Tensor) -> Tensor:
        """Exp: tangent ``(*b, dim)`` → element ``(*b, n, n)``."""
        return self._run("exp", self._tangent(xi, "exp"))

    def log(self, g: Tensor) -> Tensor:
        """Log: element → tangent, principal branch (rotation angle in [0, π])."""
        return self._run("log", self._element(g, "log"))

    def compose(self, g: Tensor, h: Tensor) -> Tensor:
        """The group product ``g · h`` (broadcast over batch dims)."""
        return self._run("compose", self._element(g, "compose"), self._element(h, "compose"))

    def inverse(self, g: Tensor) -> Tensor:
        """The group inverse ``g⁻¹``."""
        return self._run("inverse", self._element(g, "inverse"))

    def act(self, g: Tensor, points: Tensor) -> Tensor:
        """Transform points ``(*b, point_dim)`` by the pose ``g`` (``R p + t``)."""
        g = self._element(g, "act")
        if not isinstance(points, Tensor) or points.ndim < 1 or points.shape[-1] != self.point_dim:
            raise ValueError(
                f"{self.name}.act: expected points of shape (*batch, {self.point_dim}), got {_shape(points)}"
            )
        return self._run("act", g, points)

    def identity(
        self,
        batch_shape: BatchShape = (),
        *,
        device: torch.device | str | None = None,
        dtype: torch.dtype | None = None,
    ) -> Tensor:
        """The identity element, repeated over ``batch_shape``."""
        n = self.matrix_dim
        eye = torch.eye(n, device=device, dtype=dtype or torch.get_default_dtype())
        return eye.expand(*_as_shape(batch_shape), n, n).clone()

    def hat(self, xi: Tensor) -> Tensor:
        """Tangent vector → Lie algebra matrix ``(*b, n, n)``."""
        return self._run("hat", self._tangent(xi, "hat"))

    def vee(self, X: Tensor) -> Tensor:
        """Lie algebra matrix → tangent vector (inverse of ``hat``)."""
        return self._run("vee", self._element(X, "vee"))

    def adjoint(self, g: Tensor) -> Tensor:
        """Adjoint matrix ``(*b, dim, dim)``: ``g · Exp(z) · g⁻¹ = Exp(Ad(g) z)``."""
        return self._run("adjoint", self._element(g, "adjoint"))

    def jac_left(self, xi: Tensor) -> Tensor:
        """Left Jacobian J_l(ξ), ``(*b, dim, dim)``: ``Exp(ξ + δ) ≈ Exp(J_l δ) Exp(ξ)``."""
        return self._run("jac_left", self._tangent(xi, "jac_left"))

    def jac_right(self, xi: Tensor) -> Tensor:
        """Right Jacobian J_r(ξ) = J_l(−ξ): ``Exp(ξ + δ) ≈ Exp(ξ) Exp(J_r δ)``."""
        return self._run("jac_right", self._tangent(xi, "jac_right"))

    def jac_left_inv(self, xi: Tensor) -> Tensor:
        """J_l(ξ)⁻¹ in closed form."""
        return self._run("jac_left_inv", self._tangent(xi, "jac_left_inv"))

    def jac_right_inv(self, xi: Tensor) -> Tensor:
        """J_r(ξ)⁻¹ in closed form."""
        return self._run("jac_right_inv", self._tangent(xi, "jac_right_inv"))

    def rplus(self, g: Tensor, xi: Tensor) -> Tensor:
        """``g · Exp(ξ)``: the right perturbation of the paper's kernel (Eq. 3)."""
        return self._run("rplus", self._element(g, "rplus"), self._tangent(xi, "rplus"))

    def rminus(self, g: Tensor, h: Tensor) -> Tensor:
        """``Log(g⁻¹ · h)``, so that ``rplus(g, rminus(g, h)) = h``."""
        return self._run("rminus", self._element(g, "rminus"), self._element(h, "rminus"))

    def project(self, m: Tensor) -> Tensor:
        """The nearest valid element (rotation block re-orthonormalised by SVD, last row reset)."""
        return self._run("project", self._element(m, "project"))

    def sample_uniform(
        self,
        batch_shape: BatchShape = (),
        *,
        generator: torch.Generator | None = None,
        device: torch.device | str | None = None,
        dtype: torch.dtype | None = None,
        bound: float = 1.0,
    ) -> Tensor:
        """Haar-uniform rotation; translation (if any) uniform in the box ``[-bound, bound]^k``."""
        shape = _as_shape(batch_shape)
        dtype = dtype or torch.get_default_dtype()
        device = torch.device(device) if device is not None else torch.device("cpu")
        return self._sample_uniform(shape, generator, device, dtype, float(bound))

    def check(self, g: Tensor, *, atol: float | None = None) -> None:
        """Raise ``ValueError`` if ``g`` is not a valid element (within ``atol``)."""
        g = self._element(g, "check")
        if atol is None:
            atol = 1e-4 if g.dtype in (torch.float16, torch.bfloat16, torch.float32) else 1e-9
        err = self._element_error(g)
        worst = float(err.max()) if err.numel() else 0.0
        if not worst <= atol:  # also catches NaN
            raise ValueError(
                f"{self.name}.check: not a valid element (max constraint error {worst:.3g} > {atol:g})"
            )

    def matrix_rep(self, g: Tensor) -> Tensor:
        """A faithful matrix representation: ``compose`` is its matmul, ``exp`` its ``matrix_exp``.

        For matrix groups (SO3, SE3, SE2) it is the element itself; R3SO3, whose product is not the
        4×4 matmul, overrides it. Used by the contract tests as an independent oracle.
        """
        return self._element(g, "matrix_rep")

    def algebra_rep(self, xi: Tensor) -> Tensor:
        """The Lie algebra in the same representation as ``matrix_rep``."""
        return self.hat(xi)

    # ------------------------------------------------------------------ kernels (override)
    # Kernels receive shape-checked tensors and may assume nothing else; they must broadcast.
    @classmethod
    def _exp(cls, xi: Tensor) -> Tensor:
        raise NotImplementedError

    @classmethod
    def _log(cls, g: Tensor) -> Tensor:
        raise NotImplementedError

    @classmethod
    def _compose(cls, g: Tensor, h: Tensor) -> Tensor:
        return g @ h

    @classmethod
    def _inverse(cls, g: Tensor) -> Tensor:
        raise NotImplementedError

    @classmethod
    def _act(cls, g: Tensor, p: Tensor) -> Tensor:
        raise NotImplementedError

    @classmethod
    def _hat(cls, xi: Tensor) -> Tensor:
        raise NotImplementedError

    @classmethod
    def _vee(cls, X: Tensor) -> Tensor:
        raise NotImplementedError

    @classmethod
    def _adjoint(cls, g: Tensor) -> Tensor:
        raise NotImplementedError

    @classmethod
    def _jac_left(cls, xi: Tensor) -> Tensor:
        raise NotImplementedError

    @classmethod
    def _jac_right(cls, xi: Tensor) -> Tensor:
        return cls._jac_left(-xi)

    @classmethod
    def _jac_left_inv(cls, xi: Tensor) -> Tensor:
        raise NotImplementedError

    @classmethod
    def _jac_right_inv(cls, xi: Tensor) -> Tensor:
        return cls._jac_left_inv(-xi)

    @classmethod
    def _rplus(cls, g: Tensor, xi: Tensor) -> Tensor:
        return cls._compose(g, cls._exp(xi))

    @classmethod
    def _rminus(cls, g: Tensor, h: Tensor) -> Tensor:
        return cls._log(cls._compose(cls._inverse(g), h))

    @classmethod
    def _project(cls, m: Tensor) -> Tensor:
        raise NotImplementedError

    @classmethod
    def _element_error(cls, g: Tensor) -> Tensor:
        """Per-element max violation of the group's constraints, ``(*b,)``."""
        raise NotImplementedError

    @classmethod
    def _sample_uniform(
        cls,
        shape: tuple[int, ...],
        generator: torch.Generator | None,
        device: torch.device,
        dtype: torch.dtype,
        bound: float,
    ) -> Tensor:
        raise NotImplementedError

    # ------------------------------------------------------------------ plumbing
    def _run(self, op: str, *args: Tensor) -> Tensor:
        fn: Callable[..., Tensor] = getattr(type(self), "_" + op)
        if not self.compiled:
            return fn(*args)
        if torch.is_grad_enabled() and any(a.requires_grad for a in args):
            return _CompiledKernel.apply(type(self), op, *args)  # type: ignore[no-any-return]
        return _compiled(type(self), op)(*args)  # type: ignore[arg-type]  # classes hash by identity

    def _tangent(self, xi: Tensor, op: str) -> Tensor:
        if not isinstance(xi, Tensor) or xi.ndim < 1 or xi.shape[-1] != self.dim:
            raise ValueError(
                f"{self.name}.{op}: expected a tangent of shape (*batch, {self.dim}), got {_shape(xi)}"
            )
        if not xi.is_floating_point():
            raise TypeError(f"{self.name}.{op}: expected a floating-point tensor, got {xi.dtype}")
        return xi

    def _element(self, g: Tensor, op: str) -> Tensor:
        n = self.matrix_dim
        if not isinstance(g, Tensor) or g.ndim < 2 or g.shape[-2:] != (n, n):
            raise ValueError(
                f"{self.name}.{op}: expected an element of shape (*batch, {n}, {n}), got {_shape(g)}"
            )
        if not g.is_floating_point():
            raise TypeError(f"{self.name}.{op}: expected a floating-point tensor, got {g.dtype}")
        return g


@functools.cache
def _compiled(cls: type[LieGroup], op: str) -> Callable[..., Tensor]:
    """One ``torch.compile``d kernel per (group class, operation), shared by all instances.

    Inductor's CPU tiling heuristics leave kernels that read ``(*b, 3, 3)`` entries with stride 9
    unvectorised (measured: SO3 log 30 ms → 4–8 ms at N = 10⁶ with them off), hence the option.
    """
    kernel = getattr(cls, "_" + op)

    def call(*args: Tensor) -> Tensor:
        return kernel(*args)  # type: ignore[no-any-return]

    return _compile(call, f"{cls.name}_{op}")


_COMPILE_OPTIONS: dict[str, str | int | bool] = {"cpp.enable_tiling_heuristics": False}


def _compile(fn: Callable[..., Any], label: str) -> Callable[..., Any]:
    """``torch.compile`` with a code object of its own: Dynamo keeps its graphs per code object and
    gives each at most ``recompile_limit`` (8) variants, which kernels shared by several groups (the
    base class's ``_rplus``) or one vjp wrapper for every kernel would exhaust."""
    fn.__code__ = fn.__code__.replace(co_name=label, co_qualname=label)
    return torch.compile(fn, dynamic=None, fullgraph=True, options=dict(_COMPILE_OPTIONS))


@functools.cache
def _compiled_vjp(cls: type[LieGroup], op: str) -> Callable[..., tuple[Tensor, ...]]:
    """The vector-Jacobian product of a kernel, ``(*args, grad) → grads``, compiled like the kernel."""
    kernel = getattr(cls, "_" + op)

    def vjp(*args_and_grad: Tensor) -> tuple[Tensor, ...]:
        *args, grad = args_and_grad
        return torch.func.vjp(kernel, *args)[1](grad)  # type: ignore[no-any-return]

    return _compile(vjp, f"{cls.name}_{op}_vjp")


class _CompiledKernel(torch.autograd.Function):
    """A compiled kernel with a compiled backward (``LieGroup(compiled=True)`` under autograd).

    ``torch.compile`` alone would also differentiate, but its backward graphs refuse a second
    derivative; here ``create_graph=True`` takes the eager kernel's autograd graph instead.
    """

    @staticmethod
    def forward(ctx: Any, cls: type[LieGroup], op: str, *args: Tensor) -> Tensor:
        ctx.cls, ctx.op = cls, op
        ctx.save_for_backward(*args)
        return _compiled(cls, op)(*args)  # type: ignore[arg-type]  # classes hash by identity

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:
        args = ctx.saved_tensors
        wanted = ctx.needs_input_grad[2:]
        if torch.is_grad_enabled():  # create_graph=True: a graph for the next derivative
            out = getattr(ctx.cls, "_" + ctx.op)(*args)
            inputs = [a for a, w in zip(args, wanted, strict=True) if w]
            found = iter(torch.autograd.grad(out, inputs, grad, create_graph=True, allow_unused=True))
            return (None, None, *(next(found) if w else None for w in wanted))
        grads = _compiled_vjp(ctx.cls, ctx.op)(*args, grad.contiguous())
        return (None, None, *(g if w else None for g, w in zip(grads, wanted, strict=True)))


def _as_shape(batch_shape: BatchShape) -> tuple[int, ...]:
    if isinstance(batch_shape, int):
        return (batch_shape,)
    return tuple(int(d) for d in batch_shape)


def _shape(x: object) -> str:
    return str(tuple(x.shape)) if isinstance(x, Tensor) else type(x).__name__
