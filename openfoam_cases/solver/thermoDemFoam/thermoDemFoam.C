/*---------------------------------------------------------------------------*\
Application
    thermoDemFoam

Description
    Gas phase of an unresolved CFD-DEM coupling (OpenFOAM v1912) for the
    thermodem Python/Numba DEM code.

    Volume-averaged, incompressible gas with void fraction eps:
      d(eps)/dt + div(eps U) = 0
      d(eps U)/dt + div(eps U U) - div(eps nuEff (grad U + dev2 grad U^T))
          = epsP (g - grad p) - Ksl/rho (U - Us)
      eps rho cp (dT/dt + U.grad T) = div(eps k_eff grad T) + Sexp - Simp T
    Laminar by default; OpenFOAM's incompressible turbulence models (RAS, LES)
    are selected in constant/turbulenceProperties: nuEff = nu + nut,
    k_eff = k + rho cp nut/Prt (Prt in transportProperties, default 0.85).
    epsP = eps (Zhou et al. 2010, set II, model A; default) or 1 (model B),
    chosen by 'modelType' in constant/couplingProperties.

    One CFD time step per coupling step. Protocol (docs/coupling_protocol.md):
      start : send step i0 (initial U, T, grad p, p)
      loop  : receive step n (eps, Ksl, Us, Simp, Sexp) -> solve -> send step n
    Each frame to the DEM ends with the step's energy ledger (energyBalance.H):
    the heat through each boundary patch, the gas's energy, the particles' heat.
    Transport selected in system/couplingDict (file | socket | m2m | none);
    with m2m every processor exchanges its own cells directly with the DEM
    ranks that own them (no gather / scatter through the master).

    Stop signals (coupled runs): SIGINT or SIGTERM finish the current step,
    write the fields at its time (a restart point), send its frame with FINAL
    and the signal number (flags bits 8-15) and end with status 0; the DEM then
    stops at the same step.

\*---------------------------------------------------------------------------*/

#include "fvCFD.H"
#include "singlePhaseTransportModel.H"
#include "turbulentTransportModel.H"
#include "pimpleControl.H"
#include "fvOptions.H"
#include "dragFaces.H"
#include "wallFvPatch.H"
#include "tiedWalls.H"
#include "couplingIO.H"
#include "energyBalance.H"
#include "particleMeans.H"

#include <csignal>

// * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * //

namespace
{

// Number of a stop signal (SIGINT, SIGTERM) received, 0 if none
volatile std::sig_atomic_t stopSignal = 0;

extern "C" void onStopSignal(int signum)
{
    stopSignal = signum;
}

// Coupled runs: SIGINT/SIGTERM end the run cleanly after the current step
// (the fields are written there) instead of killing the solver mid-step.
void catchStopSignals()
{
    struct sigaction sa;
    std::memset(&sa, 0, sizeof(sa));
    sa.sa_handler = onStopSignal;
    sigemptyset(&sa.sa_mask);
    ::sigaction(SIGINT, &sa, nullptr);
    ::sigaction(SIGTERM, &sa, nullptr);
}

// Columns sent to the DEM: Ux Uy Uz T dpdx dpdy dpdz p   (SI: m/s, K, Pa/m, Pa)
Foam::List<Foam::scalarField> outgoingColumns
(
    const Foam::volVectorField& U,
    const Foam::volScalarField& T,
    const Foam::volScalarField& p,
    const Foam::dimensionedScalar& rho,
    const Foam::surfaceScalarField& phi,
    const Foam::volScalarField& eps,
    const Foam::volScalarField& epsP,
    const Foam::volScalarField& Ksl,
    const Foam::volVectorField& Us,
    const Foam::surfaceScalarField& phiI,
    const Foam::dimensionedScalar& nu,
    const Foam::dimensionedVector& g,
    const bool fluxVelocity
)
{
    using namespace Foam;
    // the gradient of the cell momentum balance (dragFaces.H): from the fields of the
    // step alone, so that a restart sends exactly what the interrupted run sent
    const volVectorField gradp
    (
        rho*dragFaces::pressureGradient(p, Ksl, rho, eps, epsP, Us, phiI, nu, g)
    );

    // Velocity for the DEM: the cell (momentum) velocity, or, with fluxVelocity,
    // reconstructed from the conservative face fluxes (superficial flux / eps),
    // which is exact for uniform flow and not disturbed next to sharp jumps of
    // Ksl (bed surface) where the collocated cell pressure gradient averages two
    // very different face gradients.
    vectorField Usend(U.primitiveField());
    if (fluxVelocity)
    {
        Usend = (fvc::reconstruct(phi)().primitiveField())/eps.primitiveField();
    }

    List<scalarField> cols(8);
    for (direction d = 0; d < 3; ++d)
    {
        cols[d] = Usend.component(d);
        cols[4 + d] = gradp.primitiveField().component(d);
    }
    cols[3] = T.primitiveField();
    cols[7] = rho.value()*p.primitiveField();
    return cols;
}

} // End anonymous namespace


int main(int argc, char *argv[])
{
    argList::addNote
    (
        "Volume-averaged incompressible gas flow and heat transfer for an"
        " unresolved CFD-DEM coupling with the thermodem DEM code"
    );

    #include "setRootCaseLists.H"
    #include "createTime.H"
    #include "createMesh.H"
    #include "createPimpleControl.H"
    #include "createFields.H"

    turbulence->validate();

    scalar cumulativeContErr = 0;

    // velocity sent to the DEM: "cell" (default, the momentum-equation velocity:
    // gas and particles exchange exactly opposite drag forces) or "flux"
    // (reconstructed from the conservative face fluxes / eps: exact mass flow,
    // free of the wiggles a collocated grid shows next to a sharp jump of Ksl)
    const word sendVelocity
    (
        couplingDict.lookupOrDefault<word>("sendVelocity", "cell")
    );
    if (sendVelocity != "flux" && sendVelocity != "cell")
    {
        FatalIOErrorInFunction(couplingDict)
            << "sendVelocity " << sendVelocity << " unknown: use flux or cell"
            << exit(FatalIOError);
    }
    const bool fluxVelocity = (sendVelocity == "flux");

    // the gas's energy ledger of the last step (energyBalance.H), sent with each frame;
    // at the start only its energy is meaningful (no step solved yet)
    List<scalar> energyLedger(energyBalance::size(mesh), 0.0);
    {
        tmp<volScalarField> tnut;
        if (turbulentFlow)
        {
            tnut = turbulence->nut();
        }
        energyLedger = energyBalance::ledger
        (
            T, eps, phi,
            energyBalance::diffusivity(eps, alphaGas, tnut.valid() ? &tnut() : nullptr, Prt.value())(),
            rho, cp, Sexp, Simp, nullptr
        );
    }

    // ------------------------------------------------------------- step i0
    if (coupling.active())
    {
        catchStopSignals();
        coupling.send
        (
            runTime.timeIndex(),
            runTime.value(),
            outgoingColumns(U, T, p, rho, phi, eps, epsP, Ksl, Us, phiI, nu, g, fluxVelocity),
            energyLedger,
            0
        );
    }

    Info<< "\nStarting time loop\n" << endl;

    while (runTime.loop())
    {
        const label step = runTime.timeIndex();
        Info<< "Time = " << runTime.timeName() << "  coupling step " << step
            << nl << endl;

        // --------------------------------------------------------- receive
        label peerFlags = 0;
        if (coupling.active())
        {
            List<scalarField> in;
            peerFlags = coupling.receive(step, in, tiedFirstColumn + tied.nColumns());
            if (!tied.read(in, tiedFirstColumn))
            {
                FatalErrorInFunction
                    << "non-finite particle heat of a tied wall"
                    << " [peer: DEM, coupling step " << step << ']' << exit(FatalError);
            }

            scalarField& epsI = eps.primitiveFieldRef();
            scalarField& KslI = Ksl.primitiveFieldRef();
            vectorField& UsI = Us.primitiveFieldRef();
            scalarField& SimpI = Simp.primitiveFieldRef();
            scalarField& SexpI = Sexp.primitiveFieldRef();

            label nBad = 0;
            forAll(epsI, i)
            {
                const scalar e = in[0][i];
                const scalar k = in[1][i];
                const scalar si = in[5][i];
                const scalar se = in[6][i];
                if
                (
                    !std::isfinite(e) || e <= 0 || e > 1 + 1e-6
                 || !std::isfinite(k) || k < 0
                 || !std::isfinite(si) || si < 0 || !std::isfinite(se)
                 || !std::isfinite(in[2][i]) || !std::isfinite(in[3][i])
                 || !std::isfinite(in[4][i])
                )
                {
                    if (nBad < 5)
                    {
                        Pout<< "bad DEM data in local cell " << i
                            << ": eps " << e << " Ksl " << k << " Simp " << si
                            << " Sexp " << se << endl;
                    }
                    ++nBad;
                }
                epsI[i] = min(max(e, epsMin), 1.0);
                KslI[i] = k;
                UsI[i] = vector(in[2][i], in[3][i], in[4][i]);
                SimpI[i] = si;
                SexpI[i] = se;
            }
            reduce(nBad, sumOp<label>());
            if (nBad)
            {
                FatalErrorInFunction
                    << nBad << " cells with non-physical data (need 0 < eps <= 1,"
                    << " Ksl >= 0, Simp >= 0, finite values)"
                    << " [peer: DEM, coupling step " << step << ']'
                    << exit(FatalError);
            }
            if (particleFields)
            {
                scalarField& a = alphap().primitiveFieldRef();
                vectorField& aU = alphapUp().primitiveFieldRef();
                scalarField& aT = alphapTp().primitiveFieldRef();
                label nBadP = 0;
                forAll(a, i)
                {
                    a[i] = in[7][i];
                    aU[i] = vector(in[8][i], in[9][i], in[10][i]);
                    aT[i] = in[11][i];
                    if
                    (
                        !std::isfinite(a[i]) || a[i] < 0 || !std::isfinite(aT[i])
                     || !std::isfinite(aU[i].x()) || !std::isfinite(aU[i].y())
                     || !std::isfinite(aU[i].z())
                    )
                    {
                        ++nBadP;
                    }
                }
                reduce(nBadP, sumOp<label>());
                if (nBadP)
                {
                    FatalErrorInFunction
                        << nBadP << " cells with non-finite particle fields (alphap >= 0)"
                        << " [peer: DEM, coupling step " << step << ']' << exit(FatalError);
                }
                alphap().correctBoundaryConditions();
                alphapUp().correctBoundaryConditions();
                alphapTp().correctBoundaryConditions();
            }
            eps.correctBoundaryConditions();
            Ksl.correctBoundaryConditions();
            Us.correctBoundaryConditions();
            Simp.correctBoundaryConditions();
            Sexp.correctBoundaryConditions();
            if (modelA)
            {
                epsP = eps;
            }
        }

        // Courant number on the interstitial velocity
        {
            const scalarField sumPhi
            (
                fvc::surfaceSum(mag(phi)/fvc::interpolate(eps))().primitiveField()
            );
            const scalar CoNum =
                0.5*gMax(sumPhi/mesh.V().field())*runTime.deltaTValue();
            Info<< "Courant Number max: " << CoNum << endl;
        }

        // --------------------------------------------------------- PIMPLE
        while (pimple.loop())
        {
            #include "UEqn.H"

            while (pimple.correct())
            {
                #include "pEqn.H"
            }

            if (pimple.turbCorr())
            {
                laminarTransport.correct();
                turbulence->correct();
            }
        }

        #include "TEqn.H"

        if (particleFields)
        {
            // the particles' heat into the gas of this step, as TEqn took it (T implicit)
            Qp() = Sexp - Simp*T;
            Qp().correctBoundaryConditions();
        }

        // --------------------------------------------------------- send
        // a stop signal on any processor ends the run after this step
        label stopSig = label(stopSignal);
        reduce(stopSig, maxOp<label>());

        const bool lastStep =
            (peerFlags & demCoupling::flagFinal)
         || stopSig
         || runTime.value() > runTime.endTime().value() - 0.5*runTime.deltaTValue();

        if (lastStep)
        {
            runTime.writeNow();
        }
        else
        {
            runTime.write();
        }

        if (coupling.active())
        {
            coupling.send
            (
                step,
                runTime.value(),
                outgoingColumns(U, T, p, rho, phi, eps, epsP, Ksl, Us, phiI, nu, g, fluxVelocity),
                energyLedger,
                (lastStep ? demCoupling::flagFinal : 0)
              | (label(stopSig & 0xff) << demCoupling::signalShift)
            );
        }

        runTime.printExecutionTime(Info);

        if ((peerFlags & demCoupling::flagFinal) || stopSig)
        {
            // the run ends here, not in runTime.loop(): the function objects of this last
            // step run as Time::run runs them at the end (the time averages and their
            // state, functionObjectProperties, into the time folder just written)
            runTime.functionObjects().execute();
            runTime.functionObjects().end();
        }

        if (peerFlags & demCoupling::flagFinal)
        {
            Info<< "DEM peer signalled the final step " << step << endl;
            break;
        }
        if (stopSig)
        {
            Info<< "Stopped by signal " << stopSig << " after step " << step
                << " (fields written at t = " << runTime.timeName() << ")" << endl;
            break;
        }
    }

    Info<< "End\n" << endl;

    return 0;
}


// ************************************************************************* //
