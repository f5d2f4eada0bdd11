"""fem3d's code generator: SymPy derivations rendered by Jinja2 into NumPy and C kernels.

Stages, each with a named input and output:

1. **derive** (:mod:`codegen.derive`): a material's ``psi(F, params)``
   (:mod:`codegen.materials`) and the linear tetrahedron (:mod:`codegen.tet`)
   -> exact SymPy expressions (``P = dpsi/dF``, ``dP/dF``, element energy, gradient,
   Hessian, shape functions, mass matrix) in the conventions of :mod:`codegen.conventions`.
   Each derivative is taken twice, directly in the entries of ``F`` and by the chain rule
   through the invariants (``J``, ``I1``, ...) that :mod:`codegen.invariants` finds in
   ``psi``; the variant with fewer operations is kept.
   Higher-order tetrahedra (P2) are described by :mod:`codegen.elements` (Lagrange nodes,
   shape functions, exact mass, quadrature rules); :mod:`codegen.element_kernels` makes their
   quadrature kernels (the material's steps per point, summed; in C one shared loop per
   kernel kind calling each material's steps at one ``F``) and documents their calling
   convention; :mod:`codegen.quadrature_check` measures each rule's energy error.
2. **spec** (:mod:`codegen.spec`): expressions -> a frozen :class:`~codegen.spec.KernelSpec`
   per kernel: inputs and their shapes, CSE'd intermediates, outputs, operation count.
   Back-end independent.
3. **render** (:mod:`codegen.render`): a :class:`~codegen.spec.ModuleSpec` -> source text,
   through ``templates/<backend>/module.*.jinja`` and one expression printer per back end.
4. **write** (:mod:`codegen.__main__`): source text -> files under ``generated/`` with a
   banner naming the template, the source module and the SymPy version.

Run ``python -m codegen`` (``make codegen``) to regenerate, ``python -m codegen --check`` to
diff against the committed files, ``python -m codegen show neo_hookean.hessian --backend c``
to print one kernel's source.
"""
