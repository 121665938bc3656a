"""fuelid export: a model.json as a MATLAB idpoly script or a .mat file (ident.export)."""
from fuelid.ident.export import write_mat, write_matlab
from fuelid.ident.modelfile import load_model


def add_arguments(p):
    p.add_argument("model", metavar="MODEL.json", help="model file (fuelid identify, fetch or the daemon's snapshot)")
    p.add_argument("--to", required=True, choices=["matlab", "mat"],
                   help="matlab: a .m script building `sys = idpoly(...)`; mat: the coefficients as a .mat file")
    p.add_argument("-o", "--output", required=True, metavar="FILE", help="file to write (model.m or model.mat)")


def run(args) -> int:
    model = load_model(args.model)
    if args.to == "matlab":
        write_matlab(model, args.output, source=args.model)
    else:
        write_mat(model, args.output)
    return 0
